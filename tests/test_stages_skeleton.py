"""The stage skeleton (party.stage), the stage/library boundary and the CLI's return value."""
import ast
import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from party.config import write_params
from party.overrides import DivergingOverride, check_overrides

ROOT = Path(__file__).resolve().parents[1]
STAGES = ROOT / "src" / "party" / "stages"
BIN = Path(sys.executable).parent


def _stage_imports(path: Path) -> list[str]:
    """Modules of party.stages that ``path`` imports (absolute or relative)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("party.stages.")]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:                                   # from . import x / from .x import y
                found.append(f"party.stages.{mod or ','.join(a.name for a in node.names)}")
            elif mod == "party.stages":
                found += [f"party.stages.{a.name}" for a in node.names]
            elif mod.startswith("party.stages."):
                found.append(mod)
    return found


def test_no_stage_imports_another_stage():
    offenders = {p.name: _stage_imports(p) for p in sorted(STAGES.glob("*.py"))}
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"stage modules import other stages (move the code into the library): {offenders}"


def test_the_import_check_can_fail(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from party.stages.evaluate import load_evaluators\nfrom party.stages import train_vqvae\n"
                   "from . import prepare\n")
    assert _stage_imports(bad) == ["party.stages.evaluate", "party.stages.train_vqvae", "party.stages.prepare"]


def test_every_stage_is_built_with_the_skeleton():
    import importlib

    from party.cli import available_stages
    for name in available_stages():
        mod = importlib.import_module(f"party.stages.{name}")
        assert getattr(mod.run, "stage_name", None) == name, f"party.stages.{name}.run is not @stage({name!r})"


def _params(tmp_path: Path, *overrides: str) -> Path:
    p = tmp_path / "params.yaml"
    write_params(p, [f"paths.prepared={tmp_path / 'prepared'}", f"tracking.dir={tmp_path / 'mlruns'}",
                     "progress=false", *overrides], ROOT / "conf")
    return p


def _runs(db: Path) -> list[dict]:
    with sqlite3.connect(db) as con:
        rows = con.execute("select run_uuid, name, status from runs").fetchall()
        tags = con.execute("select run_uuid, key, value from tags").fetchall()
    out = {r: {"name": n, "status": s, "tags": {}} for r, n, s in rows}
    for r, k, v in tags:
        out[r]["tags"][k] = v
    return list(out.values())


def test_a_stage_that_raises_leaves_a_failed_run_with_the_error(tmp_path):
    from party.config import load_params
    from party.stages import cache_part_texts

    cfg = load_params(_params(tmp_path))          # no prepared index: the stage fails at its first read
    with pytest.raises(Exception) as err:
        cache_part_texts.run(cfg)
    runs = [r for r in _runs(tmp_path / "mlruns" / "mlflow.db") if r["tags"].get("party.stage") == "cache_part_texts"]
    assert len(runs) == 1 and runs[0]["status"] == "FAILED", runs
    assert "index.json" in runs[0]["tags"]["party.error"] and type(err.value).__name__ in runs[0]["tags"]["party.error"]
    art = list((tmp_path / "mlruns" / "artifacts").rglob("error.txt"))
    assert art and "Traceback" in art[0].read_text()


def test_a_generator_that_has_not_learned_fails_its_stage_unless_warned(tmp_path, monkeypatch):
    """As a collapsed tokenizer fails train_vqvae: the outputs are written (by train_generator), then
    the stage raises, so `dvc repro` stops there; `on_untrained: warn` lets it through; the random
    baseline (nothing learned by design) never fails."""
    from party.config import load_params
    from party.methods.party import PartyFamily
    from party.methods.random_codes import RandomCodesFamily
    from party.schema import ConfigError
    from party.stages import train_generator as stage_mod

    learned = {"learned": False, "final": {"val/loss": 5.4}, "untrained": {"val/loss": 5.5}}
    monkeypatch.setattr(PartyFamily, "train", classmethod(lambda cls, cfg, method, out, run: dict(learned)))
    cfg = load_params(_params(tmp_path, "generator.method=holistic"))
    with pytest.raises(RuntimeError, match=r"holistic: generator has not learned: validation loss 5.400 vs 5.500 "
                                           r"untrained .* generator.train.on_untrained=warn"):
        stage_mod.run(cfg)
    assert stage_mod.run(load_params(_params(tmp_path, "generator.method=holistic",
                                             "generator.train.on_untrained=warn")))["learned"] is False
    monkeypatch.setattr(RandomCodesFamily, "train", classmethod(lambda cls, cfg, method, out, run: {"family": "r"}))
    assert stage_mod.run(load_params(_params(tmp_path, "generator.method=random")))["family"] == "r"
    with pytest.raises(ConfigError, match="generator.train.on_untrained: 'eror' is not one of error, warn"):
        stage_mod.run(load_params(_params(tmp_path, "generator.train.on_untrained=eror")))


def test_overriding_a_source_key_at_stage_time_is_refused():
    with pytest.raises(DivergingOverride, match=r"text\.index_path"):
        check_overrides(["paths.prepared=/elsewhere"], "embed_texts", ROOT / "conf")
    # overriding the derived keys too says what the user means: allowed
    check_overrides(["paths.prepared=/x", "text.index_path=/x/index.json", "part_texts.index_path=/x/index.json",
                     "interactions.index_path=/x/index.json"], "embed_texts", ROOT / "conf")
    check_overrides(["vqvae.train.max_steps=5"], "train_vqvae", ROOT / "conf")     # nothing derived from it


RECORDER = '''
import json
from hydra.experimental.callback import Callback


class Recorder(Callback):
    def __init__(self, path):
        self.path = path

    def on_job_end(self, config, job_return, **kw):
        with open(self.path, "a") as f:
            f.write(json.dumps({"objective": config.objective, "value": job_return.return_value}) + "\\n")
'''


@pytest.mark.slow
def test_multirun_sweeper_receives_the_stage_metric(tmp_path):
    """`party prepare --multirun` (Hydra's basic sweeper): each job's return value is the stage's
    metrics dict, or the float `objective` names (what Optuna's sweeper optimises)."""
    (tmp_path / "recorder.py").write_text(RECORDER)
    params = _params(tmp_path, "dataset.synthetic.n_motions=12", "tracking.n_render_samples=0")
    out = tmp_path / "returns.jsonl"
    env = os.environ | {"PARTY_PARAMS": str(params), "PYTHONPATH": str(tmp_path), "PARTY_NO_RENDER": "1"}
    res = subprocess.run([str(BIN / "party"), "prepare", "--multirun", "objective=null,n_rejected",
                          "+hydra.callbacks.rec._target_=recorder.Recorder", f"+hydra.callbacks.rec.path={out}"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    got = {r["objective"]: r["value"] for r in map(json.loads, out.read_text().splitlines())}
    assert got["n_rejected"] == 0.0
    assert got[None]["counts"]["train"]["clips"] > 0 and got[None]["n_rejected"] == 0


def _compositions(tmp_path, monkeypatch, argv: list[str], one: bool) -> tuple[int, list]:
    """How many times Hydra composes ``argv``'s app (a one-key config), and what the app saw."""
    import hydra
    from hydra._internal.hydra import Hydra

    from party.cli import _one_composition, override_keys
    (tmp_path / "c.yaml").write_text("a: 1\n")
    calls, seen = [], []
    real = Hydra.compose_config
    monkeypatch.setattr(Hydra, "compose_config", lambda self, *a, **k: calls.append(1) or real(self, *a, **k))

    @hydra.main(version_base=None, config_path=str(tmp_path), config_name="c")
    def app(cfg):
        from hydra.core.hydra_config import HydraConfig
        seen.append((cfg.a, str(HydraConfig.get().mode)))

    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    monkeypatch.setattr(sys, "argv", ["app", *[a for a in argv if a not in overrides],      # flags first
                                      f"hydra.run.dir={tmp_path / 'out'}", f"hydra.sweep.dir={tmp_path / 'multi'}",
                                      *overrides])
    if one:
        with _one_composition(override_keys(overrides)):
            app()
    else:
        app()
    return len(calls), seen


def test_a_stage_composes_its_config_once_unless_an_override_may_set_the_mode(tmp_path, monkeypatch):
    """Hydra composes an app's config a first time only to read ``hydra.mode``; party's stages skip
    that (``party.cli._one_composition``) unless an override could set it. Same runs either way."""
    from hydra._internal.hydra import Hydra
    get_mode = Hydra.get_mode
    assert _compositions(tmp_path, monkeypatch, ["a=2"], one=False) == (2, [(2, "RunMode.RUN")])
    assert _compositions(tmp_path, monkeypatch, ["a=2"], one=True) == (1, [(2, "RunMode.RUN")])
    multi = [(2, "RunMode.MULTIRUN"), (3, "RunMode.MULTIRUN")]
    assert _compositions(tmp_path, monkeypatch, ["--multirun", "a=2,3"], one=True) == (1, multi)
    # the mode set by an override: read first, as Hydra does
    assert _compositions(tmp_path, monkeypatch, ["hydra.mode=MULTIRUN", "a=2,3"], one=True) == (2, multi)
    assert Hydra.get_mode is get_mode                                               # restored


def test_which_errors_a_stage_reports_in_one_line(tmp_path):
    """``party.cli.said``: a ``raise`` of the party package itself (the checks that name a file and
    what to run) or an ``OSError`` is its message alone; a bug in party's code (a ``KeyError`` from
    a lookup) or a library's error keeps its traceback."""
    from party.cli import error_line, said
    from party.io import require

    def caught(fn):
        try:
            fn()
        except Exception as e:                       # noqa: BLE001 - the error is what is tested
            return e
        raise AssertionError("no error")

    missing = caught(lambda: require(tmp_path / "none.json", "party prepare", "index"))
    assert said(missing) and error_line(missing).startswith(f"{tmp_path / 'none.json'}: index not found")
    oserr = caught(lambda: open(tmp_path / "absent.txt"))
    assert said(oserr) and error_line(oserr).startswith("FileNotFoundError: [Errno 2]")
    from party.cli import override_keys
    assert not said(caught(lambda: override_keys([1])))          # a bug in party's code: not a raise
    import torch
    assert not said(caught(lambda: torch.zeros(2) @ torch.zeros(3)))            # a library's error


def test_a_stage_error_is_one_line_unless_the_full_error_is_asked(tmp_path):
    """``party <stage>`` on an input that is not there: the message (the file, what to run), exit 1,
    no traceback; ``HYDRA_FULL_ERROR=1`` brings Hydra's full traceback back."""
    params = _params(tmp_path)
    env = {**os.environ, "PARTY_PARAMS": str(params), "PARTY_FORK_SERVER": "0"}
    env.pop("HYDRA_FULL_ERROR", None)

    def party(**extra):
        return subprocess.run([sys.executable, "-m", "party.cli", "cache_part_texts"], cwd=tmp_path,
                              env={**env, **extra}, capture_output=True, text=True, timeout=300)

    short = party()
    assert short.returncode == 1, short.stderr[-2000:]
    assert "Traceback" not in short.stderr and "Error executing job" not in short.stderr, short.stderr[-2000:]
    assert short.stderr.strip().splitlines()[-1] == (f"party cache_part_texts: {tmp_path / 'prepared' / 'index.json'}: "
                                                     "prepared index not found; run `party prepare`"), short.stderr[-2000:]
    full = party(HYDRA_FULL_ERROR="1")
    assert full.returncode == 1 and "Traceback" in full.stderr and "party/io.py" in full.stderr
