"""The direction of data in the code: drivers -> campaign -> recording -> estimation -> export,
with the CLI, benches and UI on top (the recording format, which the campaign writes, ranks
below the campaign as a contract both sides import). Every import of a `workcell` module (module level or inside
a function) is read from the source; a lower package importing a higher one fails here, except
the two feedback paths the README names (adaptive plans refit; the closed-loop check moves the
arm through the campaign's guard)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "workcell"

# the rank of each package: an import may only go to a rank at or below its own
RANK = {
    "_jax": 0,
    "errors": 0,
    "atomic": 0,
    "strict_json": 0,
    "kinematics": 0,
    "drivers": 1,
    # the recording format is the contract between the campaign (writes it) and the estimation
    # (reads it): the campaign imports its writer, so it ranks below the campaign
    "recording": 1.5,
    "campaign": 2,
    "estimation": 4,
    "export": 5,
    "bench": 6,
    "commands": 7,
    "tui": 7,
    "cli": 8,
}
# the feedback paths the README's "Code layout" names: (importing module, imported package)
ALLOWED_UP = {
    ("workcell.campaign.adaptive", "estimation"),
    ("workcell.campaign.identification", "estimation"),
}
ALLOWED_BACK = {
    "workcell.export.validate",
    "workcell.export.demo_step",
    "workcell.export.build",
    "workcell.export.margin",
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[str, int]]:
    """Every absolute import of the file: (module, line)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, node.lineno))
    return out


def _package(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "workcell" and len(parts) > 1 else None


def _edges():
    for path in sorted(PKG.rglob("*.py")):
        mod = _module_name(path)
        src = _package(mod)
        for target, line in _imports(path):
            yield mod, src, target, line, path


def test_every_package_has_a_rank():
    pkgs = {p.stem if p.is_file() else p.name for p in PKG.iterdir()}
    pkgs = {p for p in pkgs if not p.startswith("__")}
    assert pkgs <= set(RANK), f"packages without a rank in this test: {pkgs - set(RANK)}"


def test_imports_follow_the_direction_of_data():
    bad = []
    for mod, src, target, line, path in _edges():
        dst = _package(target)
        if src is None or dst is None or dst == src:
            continue
        if RANK[dst] <= RANK[src]:
            continue
        if (mod, dst) in ALLOWED_UP:
            continue
        bad.append(f"{path.relative_to(ROOT)}:{line} {mod} imports {target}")
    assert not bad, "imports against the direction of data:\n" + "\n".join(bad)


def test_export_reaches_back_only_for_the_guard_and_envelope():
    bad = []
    for mod, src, target, line, path in _edges():
        if src == "export" and _package(target) == "campaign" and mod not in ALLOWED_BACK:
            bad.append(f"{path.relative_to(ROOT)}:{line} {mod} imports {target}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("below", ["drivers", "kinematics", "recording", "estimation", "export"])
def test_no_simulator_below_the_top(below):
    """The estimators, recording and drivers never import the simulator (its truth)."""
    bad = [
        f"{path.relative_to(ROOT)}:{line} imports {target}"
        for mod, src, target, line, path in _edges()
        if src == below and target.split(".")[0] == "sim_devices"
    ]
    assert not bad, "\n".join(bad)
