"""``party exp show`` (party.exp_view): DVC's experiments table cut to a screen, read from the
JSON that a real ``dvc exp show --json`` prints in a throwaway git + DVC repository holding a
baseline, one experiment that ran and two queued ones."""
from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import textwrap

import pytest

from party import exp_view
from party.exp_view import fmt, headers, matches, render, rows_of

TRAIN = textwrap.dedent("""\
    import json, os, yaml
    p = yaml.safe_load(open("params.yaml"))
    lr, epochs = p["trainer"]["lr"], p["trainer"]["max_epochs"]
    os.makedirs("metrics/eval", exist_ok=True)
    json.dump({"holistic": {"fid": 12.3456 * epochs, "mm_dist": 5.0},
               "coherence": {"tc": 0.5 + lr, "sc": 0.9}}, open("metrics/eval/party.json", "w"))
    json.dump({"holistic": {"fid": 0.117}, "coherence": {"tc": 0.557, "sc": 0.73}},
              open("metrics/eval/ground_truth.json", "w"))
    json.dump({"val": {"mpjpe_mm": 100.0 / (1 + lr * 1000 * epochs)}}, open("metrics.json", "w"))
""")
PARAMS = textwrap.dedent("""\
    seed: 1234
    trainer:
      lr: 0.001
      max_epochs: 3
      optimizer: {name: adam, betas: [0.9, 0.999]}
    vqvae:
      codebook_size: 512
      very_long_nested_group_name: {deeper: {parameter_with_a_long_name: 1.23456789}}
    """)


def _run(cmd, cwd, env):
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, f"{cmd}: {res.stdout[-2000:]}\n{res.stderr[-2000:]}"
    return res


@pytest.fixture(scope="module")
def repo(tmp_path_factory):
    """A git + DVC repository: baseline (lr 0.001), experiment ``lr-high`` run, and two queued
    experiments (``nifty`` with max_epochs and codebook size changed, ``to-sgd``)."""
    d = tmp_path_factory.mktemp("dvc-exp")
    env = os.environ | {"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                        "GIT_COMMITTER_EMAIL": "t@t", "DVC_NO_ANALYTICS": "1"}
    env.pop("DVC_ROOT", None)
    dvc = [sys.executable, "-m", "dvc"]
    (d / "params.yaml").write_text(PARAMS)
    (d / "train.py").write_text(TRAIN)
    (d / "dvc.yaml").write_text(textwrap.dedent(f"""\
        stages:
          train:
            cmd: {sys.executable} train.py
            deps: [train.py]
            params: [trainer, vqvae]
            metrics:
              - metrics/eval: {{cache: false}}
              - metrics.json: {{cache: false}}
        """))
    _run(["git", "init", "-q"], d, env)
    _run([*dvc, "init", "-q"], d, env)
    _run([*dvc, "repro", "-q"], d, env)
    _run(["git", "add", "-A"], d, env)
    _run(["git", "commit", "-qm", "baseline"], d, env)
    _run([*dvc, "exp", "run", "-q", "-n", "lr-high", "-S", "trainer.lr=0.01"], d, env)
    _run(["git", "checkout", "-q", "--", "params.yaml", "metrics", "metrics.json", "dvc.lock"], d, env)
    _run([*dvc, "exp", "run", "--queue", "-n", "nifty", "-S", "trainer.max_epochs=10",
          "-S", "vqvae.codebook_size=1024"], d, env)
    _run([*dvc, "exp", "run", "--queue", "-n", "to-sgd", "-S", "trainer.optimizer.name=sgd"], d, env)
    return d, env, exp_view.run_dvc([], cwd=d)


def test_rows_are_workspace_baseline_and_every_experiment(repo):
    _, _, data = repo
    rows = {r["name"]: r for r in rows_of(data)}
    assert set(rows) == {"workspace", "master", "lr-high", "nifty", "to-sgd"} or \
        set(rows) == {"workspace", "main", "lr-high", "nifty", "to-sgd"}
    base = rows.get("master") or rows["main"]
    assert (rows["workspace"]["state"], base["state"]) == ("workspace", "baseline")
    assert (rows["lr-high"]["state"], rows["nifty"]["state"], rows["to-sgd"]["state"]) == ("done", "queued", "queued")
    assert rows["lr-high"]["params"]["params:trainer.lr"] == 0.01
    assert rows["lr-high"]["metrics"]["metrics/eval/party:coherence.tc"] == pytest.approx(0.51)
    assert rows["nifty"]["params"]["params:vqvae.codebook_size"] == 1024 and not rows["nifty"]["metrics"]


def _table(text):
    """header cells -> {experiment name: cell} of the table at the top of ``text``."""
    lines = text.splitlines()
    rule = lines[1]
    spans, i = [], 0
    while i < len(rule):
        if rule[i] == "-":
            j = i
            while j < len(rule) and rule[j] == "-":
                j += 1
            spans.append((i, j))
            i = j
        else:
            i += 1
    body = [ln for ln in lines[2:lines.index("")]] if "" in lines else lines[2:]
    cut = [[ln[a:b].strip() for a, b in spans] for ln in [lines[0], *body]]
    return {h: {r[0]: r[k] for r in cut[1:]} for k, h in enumerate(cut[0])}


def test_columns_are_headline_metrics_and_the_params_that_differ(repo):
    _, _, data = repo
    text = render(data)
    table = _table(text)
    assert list(table)[:2] == ["experiment", "state"]
    # METRICS: the party source's fid, mm_dist, tc, sc; no other metric
    assert list(table)[2:6] == ["party:fid", "party:mm_dist", "party:tc", "party:sc"]
    # only the params that differ (lr: lr-high; max_epochs, codebook: nifty; optimizer: to-sgd)
    assert sorted(list(table)[6:]) == ["optimizer.name", "trainer.lr", "trainer.max_epochs", "vqvae.codebook_size"]
    assert "seed" not in text and "betas" not in text and "parameter_with" not in text
    # 3 significant digits; queued experiments have no metrics yet
    assert table["party:fid"]["lr-high"] == "37.0" and table["party:tc"]["lr-high"] == "0.51"
    assert table["party:tc"]["nifty"] == "-" and table["vqvae.codebook_size"]["nifty"] == "1024"
    assert table["optimizer.name"]["to-sgd"] == "sgd" and table["state"]["to-sgd"] == "queued"
    # the legend names every abbreviated column in full
    assert "party:tc" in text and "metrics/eval/party:coherence.tc" in text
    assert "trainer.optimizer.name" in text
    assert max(map(len, text.splitlines())) <= exp_view.WIDTH


def test_chosen_metrics_and_params(repo):
    _, _, data = repo
    text = render(data, metrics=["mpjpe_mm", "coherence.tc"], params=["parameter_with_a_long_name", "seed"])
    table = _table(text)
    # metrics in the selectors' order (both sources' tc), each header naming its file
    assert list(table)[2:3] == ["metrics:mpjpe_mm"]
    assert sorted(list(table)[3:5]) == ["ground_truth:tc", "party:tc"]
    assert list(table)[5:] == ["…ameter_with_a_long_name", "seed"]      # elided on the left to 24
    assert set(table["seed"].values()) == {"1234"}
    assert set(table["…ameter_with_a_long_name"].values()) == {"1.23"}
    assert "vqvae.very_long_nested_group_name.deeper.parameter_with_a_long_name" in text


def test_a_thousand_differing_params_fit_the_width(repo):
    """The real case: two configs differing in many keys. Columns that do not fit are named in
    a note, not printed past the width."""
    _, _, data = repo
    wide = copy.deepcopy(data)
    ws = wide[0]["data"]["params"]["params.yaml"]["data"]
    ws["big"] = {f"group_{i}": {"some_rather_long_parameter_name": i + 0.123456} for i in range(1000)}
    for width in (160, 80):
        text = render(wide, width=width)
        assert max(map(len, text.splitlines())) <= width
        assert "more column(s) do not fit" in text
        assert "party:fid" in text.splitlines()[0]       # headline metrics come first
    assert len(render(wide, width=400).splitlines()[0]) > 160


def test_command_runs_dvc_in_the_working_dir(repo):
    d, env, _ = repo
    res = subprocess.run([sys.executable, "-m", "party.cli", "exp", "show", "--metrics", "fid", "--width", "100"],
                         cwd=d, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0].split()[:2] == ["experiment", "state"] and "ground_truth:fid" in lines[0]
    assert any(ln.split()[:2] == ["to-sgd", "queued"] for ln in lines)
    assert max(map(len, lines)) <= 100
    # flags party does not know go to dvc: without the queued ones
    res = subprocess.run([sys.executable, "-m", "party.cli", "exp", "show", "--hide-queued"],
                         cwd=d, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0 and "lr-high" in res.stdout and "to-sgd" not in res.stdout


def test_outside_a_dvc_repository_it_says_so(tmp_path):
    res = subprocess.run([sys.executable, "-m", "party.cli", "exp", "show"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, check=False,
                         env=os.environ | {"DVC_NO_ANALYTICS": "1", "GIT_CEILING_DIRECTORIES": str(tmp_path.parent)})
    assert res.returncode == 1 and "dvc exp show --json" in res.stderr and not res.stdout


def test_input_file_and_unknown_action(repo, tmp_path, capsys):
    _, _, data = repo
    (tmp_path / "exp.json").write_text(json.dumps(data))
    assert exp_view.main(["show", "--input", str(tmp_path / "exp.json"), "--width", "120"]) == 0
    assert "lr-high" in capsys.readouterr().out
    assert exp_view.main(["list"]) == 2
    assert exp_view.main(["show", "--json"]) == 2


@pytest.mark.parametrize("value, text", [
    (0.01, "0.01"), (37.0370367, "37.0"), (0.0314159, "0.0314"), (25.0, "25"), (1234, "1234"),
    (10 ** 7, "1e+07"), (12345.6, "1.23e+04"), (1.23456789, "1.23"), (True, "true"), (None, "null"),
    ([0.9, 0.999], "[0.9,0.999]"), ("adam", "adam"), (0.1 + 0.2, "0.300")])
def test_values_to_three_significant_digits(value, text):
    assert fmt(value) == text


def test_selectors_match_whole_name_endings():
    full = "metrics/eval/party:coherence.tc"
    for sel in ("tc", "coherence.tc", "party:coherence.tc", "eval/party:coherence.tc", full):
        assert matches(full, sel), sel
    for sel in ("c", "rence.tc", "arty:coherence.tc", "party", ""):
        assert not matches(full, sel), sel
    assert matches("params:trainer.lr", "trainer.lr") and not matches("params:trainer.lr", "r.lr")


def test_headers_are_the_shortest_unambiguous_endings():
    assert headers(["params:trainer.lr", "params:vqvae.optim.lr", "params:generator.optim.lr"], 2) == \
        ["trainer.lr", "vqvae.optim.lr", "generator.optim.lr"]
    assert headers(["params:seed"], 2) == ["seed"]
    assert headers(["m/a:x.fid", "m/b:x.fid", "m/b:y.fid"], 1, keep_file=True) == ["a:fid", "b:x.fid", "b:y.fid"]
    assert headers(["params:a.b_very_long_component_name_here"], 2, max_width=12) == ["…t_name_here"]
