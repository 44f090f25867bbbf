"""report.html: self-contained tables, charts and animations; rendered by headless Chromium when installed."""
import re
import shutil
import subprocess

import numpy as np
import pytest

from party.evaluation.html import bar_charts, markdown_to_html, report_html


def stat(v, ci=0.01):
    return {"mean": v, "ci95": ci, "n": 3}


RESULTS = {"ground_truth": {"holistic": {"top1": stat(0.5), "fid": stat(0.0), "mm_dist": stat(3.0)},
                            "arms": {"top1": stat(0.4)}, "coherence": {"tc": stat(0.4), "sc": stat(0.8)}},
           "recon_holistic": {"holistic": {"top1": stat(0.45)}},
           "party": {"holistic": {"top1": stat(0.3), "fid": stat(1.2)}, "arms": {"top1": stat(0.2)},
                     "coherence": {"tc": stat(0.3)}}}
TABLES = "### Table 1: standard `metrics`\n\n| Method | Top 1 ↑ |\n|---|---|\n| Real motion | 0.500±.010 |\n| party | 0.300±.010 |\n"


def _gif():
    from party.render import render_comparison
    import tempfile
    from pathlib import Path
    j = np.random.default_rng(0).normal(0, 0.3, size=(6, 22, 3)).astype(np.float32) + [0, 1, 0]
    with tempfile.TemporaryDirectory() as tmp:
        p = render_comparison([j, j], ["real", "party"], Path(tmp) / "a.gif", "t2m", fps=20, title="a person waves")
        return p.read_bytes()


def test_markdown_tables_become_html_tables():
    h = markdown_to_html(TABLES)
    assert h.count("<table>") == 1 and "<th>Top 1 ↑</th>" in h and "<td>party</td>" in h
    assert "<h3>Table 1: standard <code>metrics</code></h3>" in h and "---" not in h


def test_bar_charts_skip_reconstructions_and_missing_metrics():
    png = bar_charts(RESULTS, "holistic", ["arms", "legs"])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert bar_charts({"recon_holistic": RESULTS["recon_holistic"]}, "holistic", ["arms"]) is None


def test_report_is_self_contained():
    page = report_html(TABLES, bar_charts(RESULTS, "holistic", ["arms"]), [("a person waves", _gif())], "t")
    srcs = re.findall(r"src='([^']+)'", page)
    assert len(srcs) == 2 and all(s.startswith("data:image/") for s in srcs)
    assert "http" not in page                         # nothing to fetch


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (Debian package `chromium`)")
def test_report_renders_in_headless_chromium(tmp_path):
    page = report_html(TABLES, bar_charts(RESULTS, "holistic", ["arms"]), [("a person waves", _gif())], "t")
    path = tmp_path / "report.html"
    path.write_text(page)
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
           "--virtual-time-budget=5000", "--dump-dom", path.as_uri()]
    dom = subprocess.run(cmd, capture_output=True, text=True, timeout=120).stdout
    assert re.search(r'data-images="2"', dom) and re.search(r'data-images-ok="2"', dom), dom[:500]
    shot = tmp_path / "shot.png"
    subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}",
                    "--window-size=1200,900", path.as_uri()], capture_output=True, timeout=120)
    from PIL import Image
    img = np.asarray(Image.open(shot).convert("L"))
    assert img.std() > 5                              # not a blank page
