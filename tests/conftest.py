import os
import random
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
os.environ.setdefault("PARTY_NO_RENDER", "")
# pytest-xdist's workers share the cores: each worker's torch (in-process training) and every stage
# it starts (party repro keeps an OMP_NUM_THREADS it is given) use the worker's share, not every
# core. Set before anything imports torch. Two workers each on two threads of a 2-core machine
# oversubscribe it: OpenMP threads wait for a preempted partner, and a tokenizer fixture that
# trains in 18 s alone took 193-258 s beside the end-to-end pipeline.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // _WORKERS)))


# The files that take longest, longest first (`bash scripts/test.sh --durations=80` on 2 cores): they
# are handed out first, so that with two workers the end-to-end file runs on one from the start while
# everything else shares the other (scripts/test.sh keeps this order: xdist's --no-loadscope-reorder).
# In xdist's own order (by test count) the end-to-end file started about 370 s into the run and
# ended it alone on one core.
LONGEST_FIRST = ("tests/test_pipeline.py", "tests/test_bvh_import.py", "tests/test_slurm.py",
                 "tests/tokenizers/test_reconstruction.py", "tests/test_slurm_preempt.py",
                 "tests/test_tracking_server.py", "tests/evaluation/test_slow.py", "tests/evaluation/test_stages.py",
                 "tests/test_trainer_builder.py", "tests/test_tracking.py", "tests/test_config.py")


def pytest_collection_modifyitems(config, items):
    first = {f: k for k, f in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda it: first.get(it.nodeid.split("::", 1)[0], len(first)))   # stable: the rest keep their order


@pytest.fixture(scope="session", autouse=True)
def _fork_server(tmp_path_factory):
    """The tests' ``party <stage>`` subprocesses fork from one warm interpreter per worker, as the
    stages of ``party repro`` do (``party.forkserver``): each skips seconds of imports. One whose
    environment differs from this process's in what a library reads when it loads runs in its own
    process (a command inside a SLURM job, one with its own PYTHONPATH), as does every command with
    ``PARTY_TEST_OWN_PROCESS=1`` set for the whole run."""
    from party.forkserver import ENV, Server
    if os.environ.get("PARTY_TEST_OWN_PROCESS") == "1" or os.environ.get(ENV):
        yield
        return
    with Server(log=tmp_path_factory.mktemp("fork_server") / "log", env=dict(os.environ)) as env:
        os.environ.update(env)
        try:
            yield
        finally:
            os.environ.pop(ENV, None)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _restore_environment():
    """Each test starts from the environment the one before it started from: what a test, or what
    it called in-process, exported (mlflow.set_tracking_uri's $MLFLOW_TRACKING_URI, Lightning's
    seed_everything's PL_GLOBAL_SEED, the encoders' HF_HUB_OFFLINE) reaches no later test, and the
    tests' `party` commands keep the environment the fork server started with."""
    before = dict(os.environ)
    yield
    if dict(os.environ) != before:
        os.environ.clear()
        os.environ.update(before)


@pytest.fixture(autouse=True)
def _seed_global_rngs():
    """Each test starts from the same global RNG state, whatever ran before it (order, -k, -x)."""
    random.seed(0)
    if "numpy" in sys.modules:
        sys.modules["numpy"].random.seed(0)
    if "torch" in sys.modules:
        sys.modules["torch"].manual_seed(0)


@pytest.fixture(scope="session")
def slurm_cluster() -> dict:
    """The one-node cluster of scripts/slurm_local.sh (``scripts/test.sh`` starts it), never a real
    cluster the machine may also reach: ``$SLURM_CONF`` set to its config (here and in the returned
    environment for subprocesses), or a skip naming what is missing."""
    import shutil
    import subprocess
    conf = Path(os.environ.get("PARTY_SLURM_DIR", "/tmp/party-slurm")) / "slurm.conf"
    if not conf.exists():
        pytest.skip(f"no local SLURM cluster ({conf} missing): bash scripts/slurm_local.sh start")
    if not all(shutil.which(c) for c in ("sinfo", "sbatch", "squeue", "scontrol", "srun")):
        pytest.skip("no SLURM client commands (sinfo, sbatch, squeue, scontrol, srun): "
                    "bash scripts/slurm_local.sh start installs them")
    os.environ["SLURM_CONF"] = str(conf)
    try:
        r = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=10)
    except subprocess.TimeoutExpired:
        pytest.skip("sinfo did not answer in 10 s: no SLURM controller (bash scripts/slurm_local.sh start)")
    if r.returncode != 0 or not r.stdout.strip():
        pytest.skip(f"the local SLURM cluster does not answer ({(r.stderr or r.stdout).strip()[:200]}): "
                    "bash scripts/slurm_local.sh start")
    return dict(os.environ)
