"""The architecture, enforced: the library never imports the stages, rendering never
imports fitting, a stage never imports another stage, and every stage reads only
outputs its upstream stages declare."""

import ast
from pathlib import Path

import pytest

from pipeline.core.runner import check_contract
from pipeline.core.stage import Stage
from stages import STAGES

ROOT = Path(__file__).parents[2]


def _imported_modules(path: Path) -> set[str]:
    modules = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            modules |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            modules.add(node.module)
            modules |= {f"{node.module}.{alias.name}" for alias in node.names}
    return modules


@pytest.mark.parametrize("path", sorted((ROOT / "pipeline").rglob("*.py")), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_library_never_imports_the_stages(path):
    assert not {m for m in _imported_modules(path) if m == "stages" or m.startswith("stages.")}


@pytest.mark.parametrize(
    "path", sorted((ROOT / "pipeline" / "render").rglob("*.py")), ids=lambda p: str(p.relative_to(ROOT))
)
def test_rendering_never_imports_fitting(path):
    """fit/ builds on render/ (scenes, materials, lights), never the other way round."""
    assert not {m for m in _imported_modules(path) if m == "pipeline.fit" or m.startswith("pipeline.fit.")}


@pytest.mark.parametrize("path", sorted((ROOT / "stages").glob("*.py")), ids=lambda p: p.name)
def test_a_stage_never_imports_another_stage(path):
    if path.name == "__init__.py":
        return  # the registry lists them all
    assert not {m for m in _imported_modules(path) if m == "stages" or m.startswith("stages.")}


def test_every_stage_needs_only_declared_outputs_of_its_upstream():
    check_contract(STAGES)
    by_name = {s.name: s for s in STAGES}
    for stage in STAGES:
        assert stage.outputs, f"{stage.name} declares no outputs"
        for need in stage.needs:
            upstream, output = need.split(".")
            assert STAGES.index(by_name[upstream]) < STAGES.index(stage), need
            assert output in by_name[upstream].outputs


def _toy(name: str, needs=(), outputs=("out",), exports=()) -> Stage:
    return Stage(name, 1, object, lambda conf, inputs, out_dir: None, needs=needs, outputs=outputs, exports=exports)


@pytest.mark.parametrize(
    "stages, message",
    [
        ((_toy("a"), _toy("b", needs=("a.missing",))), "b needs a.missing, which stage a does not declare"),
        ((_toy("b", needs=("nope.out",)),), "b needs nope.out: there is no stage nope"),
        ((_toy("a", exports=("other",)),), "a exports other, which it does not declare"),
    ],
)
def test_a_need_or_export_nobody_declares_is_refused_before_anything_runs(stages, message):
    with pytest.raises(ValueError, match=message):
        check_contract(stages)
