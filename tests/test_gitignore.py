"""The project's .gitignore keeps what is set up beside the code out of ``git status`` whether it is
a folder or a symlink to one (a shared ``.venv``, ``data/`` on another disk): ``name/`` in an
ignore file matches a real folder only, so those entries have no trailing slash."""
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what a checkout may hold as a folder or as a link to one (the pipeline's outputs, Hydra's runs,
# the environment, caches and logs)
LOCAL = (".venv", "data", "outputs", "multirun", "cache", "logs", "dvc_plots")


def git(repo: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], check=False, cwd=repo, capture_output=True, text=True, timeout=60)


@pytest.fixture
def repo(tmp_path):
    """A git repository holding the project's .gitignore, and beside it the elsewhere/<name>
    folders that the links point to."""
    work = tmp_path / "work"
    work.mkdir()
    assert git(work, "init", "-q").returncode == 0
    shutil.copy2(ROOT / ".gitignore", work / ".gitignore")
    for name in LOCAL:
        target = tmp_path / "elsewhere" / name
        target.mkdir(parents=True)
        (target / "file.txt").write_text("x\n")
    return work


@pytest.mark.parametrize("kind", ["symlink", "folder"])
def test_local_folders_and_links_to_them_are_ignored(repo, kind):
    for name in LOCAL:
        if kind == "symlink":
            (repo / name).symlink_to(repo.parent / "elsewhere" / name, target_is_directory=True)
        else:
            shutil.copytree(repo.parent / "elsewhere" / name, repo / name)
    st = git(repo, "status", "--porcelain", "--untracked-files=all")
    assert st.returncode == 0, st.stderr
    shown = [line for line in st.stdout.splitlines() if not line.endswith(".gitignore")]
    assert shown == [], f"git status shows {kind}s that .gitignore should hide: {shown}"
    ci = git(repo, "check-ignore", *LOCAL)
    assert sorted(ci.stdout.split()) == sorted(LOCAL), ci.stdout


def test_the_code_of_the_same_names_is_not_ignored(repo):
    """The entries are anchored: the package's own ``data`` module and the tests' ``cache`` code
    stay tracked."""
    for rel in ("src/party/data/index.py", "src/party/text/cache.py", "tests/data/x.py", "conf/outputs.yaml"):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text("x = 1\n")
    ci = git(repo, "check-ignore", "src/party/data/index.py", "src/party/text/cache.py", "tests/data/x.py",
             "conf/outputs.yaml")
    assert ci.returncode == 1 and ci.stdout == "", ci.stdout
