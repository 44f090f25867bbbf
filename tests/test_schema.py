"""The typed config schema (party.schema): wrong types and unknown keys fail when composing,
naming the key; every option of conf/ and the committed params.yaml validate."""
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from omegaconf import DictConfig, OmegaConf

from party.config import compose, load_params, to_params, write_params
from party.schema import SCHEMA_GROUPS, Config, ConfigError, validate

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def _fails(overrides, key, *words):
    with pytest.raises(ConfigError) as e:
        compose(overrides, CONF)
    msg = str(e.value)
    assert key in msg and e.value.key.startswith(key), msg
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg
    return msg


# --------------------------------------------------------------------------- failures name the key

def test_wrong_type_fails_at_compose():
    msg = _fails(["vqvae.train.max_steps=abc"], "vqvae.train.max_steps", "'abc'", "not an int")
    assert msg.startswith("conf: ")


def test_unknown_key_fails_at_compose():
    _fails(["+vqvae.train.bogus=1"], "vqvae.train.bogus", "unknown key", "not in the schema")
    # a near miss is suggested
    _fails(["+vqvae.train.batch_sise=1"], "vqvae.train.batch_sise", "did you mean vqvae.train.batch_size")
    _fails(["+bogus_top=1"], "bogus_top", "unknown key")


@pytest.mark.parametrize("override,key", [
    ("trainer.devices=[1,x]", "trainer.devices"),
    ("eval.replications=foo", "eval.replications"),
    ("eval.coherence.sigma=high", "eval.coherence.sigma"),
    ("dataset.parts.parts.left_leg.joints=[1,a]", "dataset.parts.parts.left_leg.joints[1]"),
    ("dataset.synthetic.body.limits_deg.elbow=[0,x]", "dataset.synthetic.body.limits_deg.elbow[1]"),
    ("progress=1", "progress"),                         # an int is not a bool
    ("vqvae.train.max_steps='5'", "vqvae.train.max_steps"),   # a quoted number is a string
    ("vqvae.train.crop=null", "vqvae.train.crop"),      # not Optional
    ("+vqvae.tokenizers.holistic.lte.enabled=2", "vqvae.tokenizers.holistic.lte.enabled"),
    ("+vqvae.tokenizers.holistic.bogus=1", "vqvae.tokenizers.holistic.bogus"),
    ("vqvae.model=5", "vqvae.model"),
])
def test_wrong_type_in_nested_group_fails(override, key):
    _fails([override], key)


@pytest.mark.parametrize("override,key,words", [
    ("eval.replications=0", "eval.replications", ["0 is out of range", ">= 1"]),
    ("vqvae.train.batch_size=0", "vqvae.train.batch_size", [">= 1"]),
    ("generator.train.max_steps=-5", "generator.train.max_steps", ["-5", ">= 1"]),
    ("generator.model.dropout=1.5", "generator.model.dropout", ["< 1"]),
    ("generator.model.cond_drop=1", "generator.model.cond_drop", ["< 1"]),
    ("generator.generate.top_p=0", "generator.generate.top_p", ["> 0"]),
    ("generator.generate.top_p=1.5", "generator.generate.top_p", ["<= 1"]),
    ("generator.generate.temperature=0", "generator.generate.temperature", ["> 0"]),
    ("generator.optim.lr=-1e-4", "generator.optim.lr", ["> 0"]),
    ("generator.corruption.prob=2", "generator.corruption.prob", ["<= 1"]),
    ("generator.train.bucket_pool=-1", "generator.train.bucket_pool", [">= 0"]),
    ("generator.model.max_tokens=1", "generator.model.max_tokens", [">= 2"]),
])
def test_out_of_range_values_fail_at_compose(override, key, words):
    """Bounds without which a stage cannot run: a count of 0, a probability above 1, a scale of 0."""
    _fails([override], key, *words)


def test_range_edges_and_nullable_bounded_keys_pass():
    compose(["generator.generate.top_p=1", "generator.generate.top_p=null", "generator.generate.top_k=null",
             "generator.model.dropout=0", "generator.train.bucket_pool=0", "generator.generate.cond_scale=0",
             "vqvae.train.threads=null", "generator.optim.lr_after=0", "eval.replications=1"], CONF)


def test_missing_key_fails():
    _fails(["~vqvae.train.crop"], "vqvae.train.crop", "missing key")


def test_valid_overrides_and_unions_pass():
    compose(["trainer.devices=[0,1]", "eval.sources.generated=[runs/a,runs/b]", "vqvae.train.threads=null",
             "+vqvae.tokenizers.holistic.train.max_steps=3", "+vqvae.tokenizers.arms.lte.enabled=false",
             "eval.coherence.end_joints={left_arm: 20}", "dataset.fps=25"], CONF)
    compose(["trainer=gpu", "trainer.devices=2"], CONF)


def test_party_params_refuses_and_writes_nothing(tmp_path):
    out = tmp_path / "params.yaml"
    with pytest.raises(ConfigError, match=r"vqvae\.train\.max_steps"):
        write_params(out, ["vqvae.train.max_steps=abc"], CONF)
    with pytest.raises(ConfigError, match=r"vqvae\.train\.bogus"):
        write_params(out, ["+vqvae.train.bogus=1"], CONF)
    assert not out.exists()


def test_cli_params_names_the_key(tmp_path):
    (tmp_path / "conf").symlink_to(CONF)
    r = subprocess.run([sys.executable, "-m", "party.cli", "params", "vqvae.train.max_steps=abc"],
                       cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode != 0 and "vqvae.train.max_steps" in r.stderr
    assert not (tmp_path / "params.yaml").exists()


def test_cli_params_fails_before_touching_the_kept_choices(tmp_path, monkeypatch):
    """A bad value never reaches conf/local/choices.yaml, not even for a moment: every other
    composition of conf/ (another shell's, a test's, a stage's) reads that file."""
    import party.config
    from party.cli import cmd_params

    def touched(*a, **k):
        raise AssertionError("persist_choices called for a bad value")
    monkeypatch.setattr(party.config, "persist_choices", touched)
    (tmp_path / "conf").symlink_to(CONF)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"vqvae\.train\.max_steps"):
        cmd_params(["vqvae.train.max_steps=abc"])


# --------------------------------------------------------------------------- what validates

def test_schema_covers_every_group_and_is_a_structured_config():
    groups = {p.name for p in CONF.iterdir() if p.is_dir()} - {"experiment", "sweep", "hydra", "local"}
    assert groups == set(SCHEMA_GROUPS)
    OmegaConf.structured(Config)            # registrable in Hydra's ConfigStore


@pytest.mark.parametrize("group", sorted(SCHEMA_GROUPS))
def test_every_group_option_validates(group):
    options = _options(group) or [None]
    for option in options:
        overrides = [f"{group}={option}"] if option else []
        if group == "dataset" and option in ("humanml3d", "kit"):
            overrides.append("dataset.root=/nonexistent")
        validate(compose(overrides, CONF), f"{group}={option}")


@pytest.mark.parametrize("experiment", _options("experiment"))
def test_every_experiment_validates(experiment):
    validate(compose([f"experiment={experiment}"], CONF))


def test_committed_params_yaml_validates():
    cfg = load_params(ROOT / "params.yaml")
    assert isinstance(cfg, DictConfig)
    validate(yaml.safe_load((ROOT / "params.yaml").read_text()), "params.yaml")


def test_load_params_names_file_and_key(tmp_path):
    params = to_params(compose([], CONF))
    params["vqvae"]["train"]["max_steps"] = "abc"
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump(params))
    with pytest.raises(ConfigError, match=r"^params\.yaml: vqvae\.train\.max_steps: 'abc' is not an int"):
        load_params(p)


def _sweep_points(name):
    import itertools
    spec = yaml.safe_load((CONF / "sweep" / f"{name}.yaml").read_text())
    axes = [list(a.values()) for a in spec["axes"].values()]
    return [list(spec.get("fixed") or []) + [o for ov in combo for o in (ov or [])]
            for combo in itertools.product(*axes)]          # excluded points included: their keys must exist too


@pytest.fixture(scope="module")
def composed_params():
    return to_params(compose([], CONF))


@pytest.mark.parametrize("name", _options("sweep"))
def test_sweep_point_overrides_are_schema_keys(name, composed_params):
    """Every point of conf/sweep/<name>.yaml sets keys that exist, to values of the schema's types
    (applied as vq_ablation does: to the composed config, values parsed as YAML)."""
    import copy
    points = _sweep_points(name)
    assert points
    for overrides in points:
        cfg = copy.deepcopy(composed_params)
        for o in overrides:
            key, value = o.split("=", 1)
            assert _update(cfg, key, yaml.safe_load(value)), f"{name}: {o}: no such key"
        validate(cfg, f"sweep {name}")


def _update(cfg: dict, key: str, value) -> bool:
    """``OmegaConf.update(cfg, key, value, merge=True)`` on plain data (a mapping merges into a
    mapping, anything else replaces); False if ``key`` is not in ``cfg``."""
    *path, last = key.split(".")
    for k in path:
        if not isinstance(cfg, dict) or k not in cfg:
            return False
        cfg = cfg[k]
    if not isinstance(cfg, dict) or last not in cfg:
        return False
    from party.tokenizers.config import _merge          # the project's recursive merge of mappings
    cfg[last] = _merge(cfg[last], value) if isinstance(cfg[last], dict) and isinstance(value, dict) else value
    return True


def test_update_on_plain_data_is_omegaconfs():
    base = {"a": {"b": 1, "c": {"d": [1, 2], "e": "x"}}, "f": 2}
    for key, value in (("a.c", {"e": "y", "g": 3}), ("a.c.d", [3]), ("f", {"z": 1}), ("a", {"c": {"d": None}})):
        ours, theirs = yaml.safe_load(yaml.safe_dump(base)), OmegaConf.create(base)
        assert _update(ours, key, value)
        OmegaConf.update(theirs, key, value, merge=True)
        assert ours == OmegaConf.to_container(theirs), key
    assert not _update({"a": {}}, "a.b", 1) and not _update({"a": 1}, "a.b", 1)


def test_sweep_files_are_well_formed_grids(tmp_path):
    from party.sweep import expand, load_sweep
    for name in _options("sweep"):
        kind = ("method",) if name.startswith("gen_") else ("stream",)      # gen_ablation | vq_ablation
        assert expand(load_sweep(name, CONF / "sweep", required=kind))
    tab5 = expand(load_sweep("gen_tab5", CONF / "sweep", required=("method",)))
    assert len(tab5) == 7 and "off-on-off" not in [p["label"] for p in tab5]     # PTG alone excluded (paper)
    ex = tmp_path / "ex.yaml"
    ex.write_text("method: party\naxes: {a: {x: [], y: []}}\nexclude: [{a: z}]\n")
    with pytest.raises(ValueError, match="exclude"):
        load_sweep(str(ex), required=("method",))
    bad = tmp_path / "bad.yaml"
    bad.write_text("stream: holistic\naxes: {window: {}}\n")
    with pytest.raises(ValueError, match="non-empty"):
        load_sweep(str(bad), required=("stream",))


# --------------------------------------------------------------------------- what validate returns

def test_validate_returns_the_values_as_given():
    cfg = compose([], CONF)
    out = validate(cfg)
    assert isinstance(out, DictConfig) and not OmegaConf.is_readonly(out)
    assert OmegaConf.to_container(out) == to_params(cfg)          # resolved, nothing added
    assert "crop_len" not in out.dataset and "arch" not in out.text     # absent optional keys stay absent
    assert type(out.dataset.fps) is type(cfg.dataset.fps)               # no int -> float coercion
    OmegaConf.merge(out, {"vqvae": {"train": {"extra": 1}}})            # plain, non-struct: callers may add keys
    out.new_key = 1


def test_validate_plain_dict_partial_and_interpolations():
    params = to_params(compose([], CONF))
    assert validate(params, "params.yaml").vqvae.train.max_steps == params["vqvae"]["train"]["max_steps"]
    small = {"seed": 0, "vqvae": {"train": {"max_steps": 3}}}
    with pytest.raises(ConfigError, match="missing key"):
        validate(small)
    validate(small, partial=True)
    with pytest.raises(ConfigError, match=r"vqvae\.train\.max_steps"):
        validate({"vqvae": {"train": {"max_steps": "x"}}}, partial=True)
    with pytest.raises(ConfigError, match=r"unknown key vqvae\.trian"):
        validate({"vqvae": {"trian": {}}}, partial=True)
    # interpolations are resolved before checking
    cfg = OmegaConf.create({"seed": "${paths.n}", "paths": {"n": 3, "prepared": "x"}})
    with pytest.raises(ConfigError, match=r"unknown key paths\.n"):
        validate(cfg, partial=True)
    with pytest.raises(ConfigError, match="seed"):
        validate({"seed": "${progress}", "progress": True}, partial=True)      # resolves to a bool
