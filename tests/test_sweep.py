"""party.sweep.run_grid for unattended sweeps: status.json, failures recorded, resume reuses done points."""
import pytest
from omegaconf import OmegaConf

from party.cli import main
from party.sweep import expand, load_sweep, read_status, run_grid


def _setup(tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text("name: g\naxes:\n  a: {x: [v.a=1], y: [v.a=2], z: [v.a=3]}\n")
    cfg = OmegaConf.create({"tracking": {"enabled": False}, "v": {"a": 0}})
    return load_sweep(str(grid)), cfg, tmp_path / "out"


def test_a_failing_point_is_recorded_the_rest_run_and_the_stage_fails(tmp_path, capsys):
    spec, cfg, out = _setup(tmp_path)
    calls, fail = [], {"label": "y"}

    def point(pcfg, p, run):
        calls.append(p["label"])
        if p["label"] == fail["label"]:
            raise ValueError("boom")
        return {"value": pcfg.v.a * 10}

    with pytest.raises(RuntimeError, match=r"1 of 3 points failed \(y\)"):
        run_grid(cfg, spec, "s", point, out, ["point", "value", "status"])
    assert calls == ["x", "y", "z"]
    st = read_status(out)
    assert {k: v["status"] for k, v in st["points"].items()} == {"x": "done", "y": "failed", "z": "done"}
    assert st["points"]["y"]["error"] == "ValueError: boom"
    assert "| y |  | failed |" in (out / "table.md").read_text()
    assert main(["sweep-status", str(out)]) == 1
    assert "2 done, 0 running, 1 failed, 0 pending" in capsys.readouterr().out

    # the rerun retries only the failed point and reuses the others' rows
    calls.clear()
    fail["label"] = None                # the cause is fixed; the configs are unchanged
    rows = run_grid(cfg, spec, "s", point, out, ["point", "value"])
    assert calls == ["y"]
    assert [r["value"] for r in rows] == [10, 20, 30]
    assert main(["sweep-status", str(out)]) == 0


def test_a_changed_point_config_reruns_that_point(tmp_path):
    spec, cfg, out = _setup(tmp_path)
    calls = []
    point = lambda pcfg, p, run: calls.append(p["label"]) or {"value": pcfg.v.a}  # noqa: E731
    run_grid(cfg, spec, "s", point, out, ["point", "value"])
    cfg.v.other = 1                     # every point's config changes
    calls.clear()
    run_grid(cfg, spec, "s", point, out, ["point", "value"])
    assert calls == ["x", "y", "z"]
    (out / "status.json").write_text("{oops")
    with pytest.raises(ValueError, match="status.json"):
        read_status(out)
    assert main(["sweep-status", str(tmp_path / "nowhere")]) == 2
    assert len(expand(spec)) == 3
