"""The documents a user reads match the project: README is a manual of at most 300 lines whose
links resolve, docs/architecture.md maps every package and every stage (its stage table agrees
with dvc.yaml and with party/stages/), and every `party` command README names exists."""
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
ARCH = ROOT / "docs" / "architecture.md"
PKG = ROOT / "src" / "party"


def _links(md: Path) -> list[str]:
    return [t for t in re.findall(r"\]\(([^)\s]+)\)", md.read_text()) if "://" not in t]


def test_readme_is_a_short_manual():
    lines = README.read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; at most 300 (details go to docs/)"
    text = README.read_text()
    for must in ("bash scripts/run_default.sh", "bash scripts/test.sh", "docs/results.md"):
        assert must in text, must


def test_every_relative_link_in_readme_and_docs_resolves():
    bad = []
    for md in [README, *sorted((ROOT / "docs").glob("*.md"))]:
        for target in _links(md):
            path = target.split("#")[0]
            if path and not (md.parent / path).exists():
                bad.append(f"{md.relative_to(ROOT)}: {target}")
    assert not bad, "links to nothing:\n" + "\n".join(bad)


def _stage_table() -> dict[str, str]:
    text = ARCH.read_text()
    section = text[text.index("## Stages"):]
    rows = re.findall(r"^\| (\w+) \| (yes[^|]*|no) \|", section, flags=re.M)
    return {name: where for name, where in rows}


def test_architecture_stage_table_matches_dvc_yaml_and_the_stage_modules():
    table = _stage_table()
    modules = {p.stem for p in (PKG / "stages").glob("*.py") if p.stem != "__init__"}
    # the stage modules dvc.yaml's stages run (train_part_vqvae@<part> runs train_vqvae)
    in_dvc = {st.get("do", st)["cmd"].split()[1] for st in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"].values()}
    assert set(table) == modules, (sorted(set(table) ^ modules), "docs/architecture.md vs party/stages/")
    assert {s for s, w in table.items() if w.startswith("yes")} == in_dvc, "docs/architecture.md vs dvc.yaml"


def test_architecture_map_names_every_module_and_package():
    text = ARCH.read_text()
    block = text[text.index("```\nsrc/party/"):]
    block = block[:block.index("```", 4)]
    names = {p.stem for p in PKG.glob("*.py") if p.stem != "__init__"}
    names |= {p.name for p in PKG.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    missing = sorted(n for n in names if not re.search(rf"(^|\s|/){re.escape(n)}(\.py|/)", block, flags=re.M))
    assert not missing, f"docs/architecture.md's map does not name: {missing}"


def test_every_party_command_in_readme_exists():
    from party import cli

    commands = set(re.findall(r"`party ([a-z_-]+)", README.read_text()))
    known = set(cli.available_stages()) | {"params", "stages", "sweep-status", "repro", "convert-checkpoint",
                                           "generate", "results", "exp", "submit"}
    source = (PKG / "cli.py").read_text()
    for c in commands - set(cli.available_stages()):
        assert f'"{c}"' in source, f"README names `party {c}`, which cli.py does not handle"
    assert commands <= known | {"<stage>"}, sorted(commands - known)
