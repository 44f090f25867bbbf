"""The project's files state what is chosen and why, not when or in which numbered work period:
no "session <n>", no "S<n>" shorthand for one, no file named after one (``<grid>_s<n>.yaml``), no
dated measurement (``<yyyy>-<mm>-<dd>``). A number belongs with the command that reproduces it.

Every file git tracks, plus untracked files git does not ignore (what the next commit adds), is
scanned: its path, and its text unless it is binary (a NUL byte in its first 8 KB). A hit is
reported as ``path:line: what: text``.

``S`` + number is also how the paper names its supplementary tables and figures (Tab. S13,
Tables S3-S5, Fig. S5), so it counts as a hit only without a cue to the paper: a cue (Tab.,
Table(s), Fig(s)., App., paper, SPEC) earlier on its line or on the line before, or the token
quoted as a literal (``"S3"``, a table key in code).
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: numbered work periods: "session <n>", "sessions <n>-<m>", "Session #<n>", "session-<n>", "sitting <n>"
PERIOD = re.compile(r"\b(?:sessions?|sittings?)[ \t#-]*\d", re.IGNORECASE)
#: the "S12" shorthand (case-sensitive: ``s0``, ``s1`` are ordinary variable names)
S_NUMBER = re.compile(r"(?<!\w)S\d{1,2}\b")
#: a cue that an S-number is the paper's: Tab. S12, Table S3, Tables 1-5 and S3-S5, Fig. S5
PAPER_CUE = re.compile(r"\b(?:Tab|Tabs|Tables?|Figs?|App|paper|SPEC)\b", re.IGNORECASE)
#: ISO dates, and "<Mon> <d>, <yyyy>" / "<d> <Month> <yyyy>"
_MONTH = r"(?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Sept|Oct|Nov|Dec)[a-z]*\.?"
DATE = re.compile(rf"\b20\d\d-[01]\d-[0-3]\d\b|\b{_MONTH} [0-3]?\d, 20\d\d\b|\b[0-3]?\d {_MONTH} 20\d\d\b")
#: a file named after a work period (``<grid>_s<n>.yaml``), as a path or mentioned in a text
FILE_NAME = re.compile(r"_s\d+\.")
FILE_MENTION = re.compile(r"\w_s\d+\.(?:ya?ml|py|md|json|csv|txt|ipynb)\b")

#: (path, exact matched text) -> why it is not a work period. A date that is not a work date
#: (a package's release, a license year, a data set's version) goes here, with its reason.
ALLOWED: dict[tuple[str, str], str] = {}


def scan_text(text: str) -> list[tuple[int, str, str]]:
    """(line number, what, matched text) for every mention of a numbered work period or a date."""
    hits = []
    previous = ""
    for n, line in enumerate(text.splitlines(), 1):
        for m in PERIOD.finditer(line):
            hits.append((n, "numbered work period", m.group(0)))
        for m in S_NUMBER.finditer(line):
            before, after = line[m.start() - 1:m.start()], line[m.end():m.end() + 1]
            if before in ("'", '"') and after == before:
                continue                               # a literal: "S3", a table's key in code
            if not PAPER_CUE.search(previous + "\n" + line[:m.start()]):
                hits.append((n, "S-number without a paper cue (Tab./Table/Fig.)", m.group(0)))
        for m in DATE.finditer(line):
            hits.append((n, "date", m.group(0)))
        for m in FILE_MENTION.finditer(line):
            hits.append((n, "file named after a work period", m.group(0)))
        previous = line
    return hits


def scan_path(path: str) -> list[str]:
    """What the path's own name says: a work period in a file or folder name."""
    out = [m.group(0) for m in FILE_NAME.finditer(Path(path).name)]
    out += [m.group(0) for m in PERIOD.finditer(path)]
    return out


def project_files() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                             cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        pytest.skip(f"not a git checkout ({e})")
    return sorted({p for p in out.decode().split("\0") if p and (ROOT / p).is_file()})


def scan_project(files: list[str]) -> list[str]:
    report = []
    for rel in files:
        for what in scan_path(rel):
            if (rel, what) not in ALLOWED:
                report.append(f"{rel}: file name names a work period: {what}")
        data = (ROOT / rel).read_bytes()
        if b"\0" in data[:8192]:
            continue                                   # binary
        lines = None
        for n, what, text in scan_text(data.decode("utf-8", errors="replace")):
            if (rel, text) in ALLOWED:
                continue
            lines = lines or data.decode("utf-8", errors="replace").splitlines()
            report.append(f"{rel}:{n}: {what}: {text!r} in {lines[n - 1].strip()[:160]!r}")
    return report


def test_the_scanner_finds_planted_offenders():
    """Not vacuous: each kind of offender planted in a text is found, on its line."""
    planted = "\n".join([
        "a clean first line",
        f"measured in session {12}, the default since then",          # line 2
        f"val loss 4.48 (sessions {17}-{18}), commit abc1234",          # line 3
        "named side 87% (" + "S" + "17" + "'s models)",                 # line 4
        "timed on " + "2026" + "-12-03, 2 cores",                       # line 5
        "the paper's Tab. " + "S" + "13" + " and Tables 1-5, " + "S" + "3-" + "S" + "5",  # paper: no hit
        'rows = {"' + "S" + '3": 1}',                                   # a quoted key: no hit
        "Dec" + f" {3}, {2026}: rerun",                                  # line 8
        "party gen_ablation generator.ablation.sweep=gen_ptg_k",        # a plain grid name: no hit
        "see conf/sweep/gen_" + "s" + "13.yaml",                        # line 10
    ])
    found = {(n, what) for n, what, _ in scan_text(planted)}
    assert (2, "numbered work period") in found
    assert (3, "numbered work period") in found
    assert (4, "S-number without a paper cue (Tab./Table/Fig.)") in found
    assert (5, "date") in found and (8, "date") in found
    assert (10, "file named after a work period") in found
    assert not {n for n, _ in found} & {1, 6, 7, 9}, found
    assert scan_path("conf/sweep/gen_" + "s" + "13.yaml") and not scan_path("conf/sweep/gen_seeds.yaml")
    assert scan_path("notes/session" + f"-{7}/plan.md")


def test_the_scan_covers_the_project():
    files = project_files()
    assert "pyproject.toml" in files and "tests/test_no_history.py" in files
    assert any(f.startswith("conf/") for f in files) and any(f.startswith("src/party/") for f in files)


def test_no_file_names_a_work_period_or_a_date():
    report = scan_project(project_files())
    assert not report, (f"{len(report)} mention(s) of a numbered work period or a date; state what is "
                        "chosen, why, the numbers and the command that reproduces them:\n"
                        + "\n".join(report))
