"""Fixture builders shared by tests (no network, no real dataset needed)."""
from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from party.motion.features import joints_to_features
from party.motion.skeleton import get_skeleton

_T2M_LENGTHS = [0, .11, .11, .12, .38, .38, .14, .40, .40, .06, .12, .12,
                .16, .09, .09, .10, .12, .12, .26, .26, .25, .25]


def rest_pose(skeleton: str = "t2m") -> np.ndarray:
    sk = get_skeleton(skeleton)
    lengths = _T2M_LENGTHS if skeleton == "t2m" else [0.15] * sk.n_joints
    pos = np.zeros((sk.n_joints, 3))
    for chain in sk.kinematic_chain:
        for a, b in zip(chain[:-1], chain[1:]):
            pos[b] = pos[a] + sk.raw_offsets[b] * lengths[b]
    pos[:, 1] -= pos[:, 1].min()
    return pos


def wiggle_joints(n_frames: int, seed: int = 0, skeleton: str = "t2m") -> np.ndarray:
    """A smooth, non-trivial motion: the rest pose translated, turned and with moving limbs."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, n_frames / 20.0, n_frames)
    pos = np.repeat(rest_pose(skeleton)[None], n_frames, 0)
    pos += rng.normal(0, 0.03, (1, pos.shape[1], 3)) * np.sin(3 * t + rng.uniform(0, 6))[:, None, None]
    yaw = rng.uniform(-3, 3) + 0.6 * np.sin(0.7 * t)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x, z = pos[..., 0].copy(), pos[..., 2].copy()
    pos[..., 0], pos[..., 2] = c * x + s * z, -s * x + c * z
    pos[..., 0] += (0.4 * t)[:, None] + rng.uniform(-2, 2)
    pos[..., 2] += (0.2 * np.sin(t))[:, None] + rng.uniform(-2, 2)
    return pos


def name_seed(name: str) -> int:
    """A seed from a name, the same in every process (``hash`` of a str is salted per process)."""
    return zlib.crc32(name.encode("utf-8")) % 1000


def write_humanml3d_fixture(root: Path, names_by_split: dict[str, list[str]], n_frames: int = 60,
                            skeleton: str = "t2m", texts: dict[str, str] | None = None) -> Path:
    """A tiny dataset in the exact HumanML3D layout (features computed from joints)."""
    sk = get_skeleton(skeleton)
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    feats_all = []
    for split, names in names_by_split.items():
        (root / f"{split}.txt").write_text("".join(n + "\n" for n in names))
        for i, name in enumerate(names):
            joints = wiggle_joints(n_frames + 1, seed=name_seed(name), skeleton=skeleton)
            feats, canon = joints_to_features(joints, sk)
            np.save(root / "new_joint_vecs" / f"{name}.npy", feats)
            np.save(root / "new_joints" / f"{name}.npy", canon[:-1].astype(np.float32))
            feats_all.append(feats)
            text = (texts or {}).get(name) or (
                "a person walks forward.#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n"
                "someone strolls ahead.#someone/PRON stroll/VERB ahead/ADV#0.0#0.0\n")
            (root / "texts" / f"{name}.txt").write_text(text)
    all_f = np.concatenate(feats_all)
    np.save(root / "Mean.npy", all_f.mean(0).astype(np.float32))
    np.save(root / "Std.npy", (all_f.std(0) + 1e-2).astype(np.float32))
    (root / "all.txt").write_text("".join(n + "\n" for v in names_by_split.values() for n in v))
    return root


# ----------------------------------------------------------------------------- end-to-end runs
PROJECT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def run_checked(cmd, cwd, env, timeout=1500) -> subprocess.CompletedProcess:
    """Run ``cmd``; assert it succeeds, showing the ends of its output if not."""
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{res.stdout[-4000:]}\n{res.stderr[-6000:]}"
    return res


def e2e_env(**extra: str) -> dict:
    """The environment of a pipeline run in a project copy: this venv's tools first on PATH, no
    PARTY_PARAMS from outside, ``extra`` variables added."""
    env = os.environ | {"PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "MPLBACKEND": "Agg",
                        "PARTY_NO_RENDER": "", "PYTHONUNBUFFERED": "1", **extra}
    env.pop("PARTY_PARAMS", None)
    return env


def copy_project(work: Path) -> Path:
    """A copy of the project (tracked and untracked-not-ignored files) at ``work``, committed in
    a fresh git repository, so that runs in it leave the working tree's data/ and mlruns/ alone."""
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
                           cwd=PROJECT, capture_output=True, text=True, check=True).stdout.split("\0")
    for rel in filter(None, files):
        src = PROJECT / rel
        if src.is_file():
            (work / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, work / rel)
    env = e2e_env()
    run_checked(["git", "init", "-q"], work, env)
    run_checked(["git", "-c", "user.email=t@t", "-c", "user.name=t", "add", "-A"], work, env)
    run_checked(["git", "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "snapshot"], work, env)
    return work


# --------------------------------------------------------------------------- scripts/mlflow_server.sh

MLFLOW_SERVER_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "mlflow_server.sh"
# variables that would send a worker's runs elsewhere or make it a non-zero rank
_SERVER_STRIP = ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI", "MLFLOW_RUN_ID", "DVC_ROOT", "DVC_EXP_NAME", "RANK",
          "LOCAL_RANK", "NODE_RANK", "SLURM_PROCID", "PARTY_MLFLOW_HOST", "PARTY_MLFLOW_PORT", "PARTY_MLFLOW_DIR",
          "PARTY_MLFLOW_WORKERS", "PARTY_MLFLOW_ALLOWED_HOSTS")


def server_env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _SERVER_STRIP}
    env.update(PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", **extra)
    return env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class MlflowServer:
    uri: str
    dir: Path
    env: dict

    def script(self, cmd: str, **extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(MLFLOW_SERVER_SCRIPT), cmd], env=self.env | extra, capture_output=True, text=True,
                              timeout=240)


def start_mlflow_server(d: Path, host: str = "127.0.0.1") -> "MlflowServer":
    """scripts/mlflow_server.sh's server in folder ``d`` on a free port (its ``uri`` as the script prints it)."""
    env = server_env(PARTY_MLFLOW_DIR=str(d), PARTY_MLFLOW_PORT=str(free_port()), PARTY_MLFLOW_HOST=host)
    srv = MlflowServer("", d, env)
    r = srv.script("start")
    assert r.returncode == 0, f"mlflow_server.sh start failed:\n{r.stdout}\n{r.stderr}"
    srv.uri = re.search(r"tracking URI: (\S+)", r.stdout).group(1)
    return srv


def stop_mlflow_server(srv: "MlflowServer") -> None:
    """Stop it through the script; its process group must be gone."""
    pid = int((srv.dir / "server.pid").read_text())
    r = srv.script("stop")
    assert r.returncode == 0 and "stopped" in r.stdout, r.stdout + r.stderr
    assert not (srv.dir / "server.pid").exists()
    try:
        os.killpg(pid, 0)
    except ProcessLookupError:
        pass                                # the server and its workers are gone
    else:
        raise AssertionError(f"mlflow server process group {pid} still alive after stop")
    r = srv.script("status")
    assert r.returncode == 1 and "not running" in r.stdout, r.stdout
