"""The house rules of ``optimizer/``, read from the source: no import circle, no method importing
another method or the orchestrator, no private name imported across modules, the web never
imported by the mathematics."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "optimizer"
#: The method modules (each behind the interface of optimizer.planner.base).
METHOD_MODULES = {"optimizer.planner.polynomial", "optimizer.planner.retimed",
                  "optimizer.planner.convex", "optimizer.planner.penalty",
                  "optimizer.planner.shooting"}
ABOVE_METHODS = {"optimizer.planner.registry", "optimizer.planner.auto",
                 "optimizer.planner.plan"}
#: Modules that hold one part of one method (split from it by concept): they serve their method
#: only, so they import no method module and nothing above the methods either.
METHOD_PARTS = {"optimizer.planner.constraint_qp", "optimizer.planner.dphi_scan",
                "optimizer.planner.legendre_qp", "optimizer.planner.level_cuts"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """``(module, names)`` of every import in the file, relative imports resolved."""
    mod = _module_name(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out: list[tuple[str, list[str]]] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [a.name for a in node.names]
            # "from . import native" imports the module optimizer.native
            subs = [f"{target}.{n}" for n in names if (PKG.parent / (
                f"{target}.{n}".replace(".", "/") + ".py")).exists()]
            out.extend((s, []) for s in subs)
            out.append((target, [n for n in names if f"{target}.{n}" not in subs]))
    return out


def _graph() -> dict[str, list[tuple[str, list[str]]]]:
    return {_module_name(p): _imports(p) for p in PKG.rglob("*.py")}


def test_no_import_circle_in_optimizer() -> None:
    graph = {m: {t for t, _ in imps if t.startswith("optimizer") and t != m}
             for m, imps in _graph().items()}
    graph = {m: {t for t in ts if t in graph} for m, ts in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                pytest.fail("import circle: " + " -> ".join(cycle))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_methods_import_no_method_nor_orchestrator() -> None:
    for m, imps in _graph().items():
        if m not in METHOD_MODULES:
            continue
        bad = sorted({t for t, _ in imps if t in (METHOD_MODULES | ABOVE_METHODS) - {m}})
        assert not bad, f"{m} imports {bad}"


def test_method_parts_import_no_method_nor_orchestrator() -> None:
    graph = _graph()
    assert METHOD_PARTS <= set(graph), sorted(METHOD_PARTS - set(graph))
    for m in METHOD_PARTS:
        bad = sorted({t for t, _ in graph[m] if t in METHOD_MODULES | ABOVE_METHODS})
        assert not bad, f"{m} imports {bad}"


def test_no_private_name_imported_across_modules() -> None:
    for m, imps in _graph().items():
        for target, names in imps:
            if target.startswith("optimizer"):
                private = [n for n in names if n.startswith("_") and not n.startswith("__")]
                assert not private, f"{m} imports private {private} from {target}"


def test_mathematics_imports_nothing_of_the_web() -> None:
    for m, imps in _graph().items():
        web = sorted({t for t, _ in imps if t.split(".")[0] in ("service", "fastapi", "uvicorn",
                                                                 "starlette", "pydantic")})
        assert not web, f"{m} imports {web}"


def test_the_transmission_law_is_written_once() -> None:
    """``th_i' = K_i cos(th_{i-1})^{m_i} u1`` appears in ``optimizer/dynamics.py`` only (bounds
    of ``cos^m`` elsewhere are not the law: they carry no input rate). The bench's generator
    and baseline and the tests' references keep their own on purpose: independent checks."""
    import re

    law = re.compile(r"cos\w*[(\[][^\n]*\*\*[^\n]*\*\s*(u1|u\[0\]|U\[0\]|F\[0\]|u\[:, 0\])")
    power = re.compile(r"power\(\s*(np\.|ca\.|math\.)?cos\(")
    offenders = [f"{p.relative_to(ROOT)}:{i}"
                 for p in PKG.rglob("*.py") if p.name != "dynamics.py"
                 for i, line in enumerate(p.read_text().splitlines(), 1)
                 if law.search(line) or power.search(line)]
    assert not offenders, offenders
    # the pattern finds the copies this replaced (the cascade's integrand, DOP853's rhs)
    assert law.search("F[s + 1] = K[s - 1] * cosx[s - 1] ** m[s - 1] * F[0]")
    assert law.search("dx[2:n + 1] = K * np.cos(x[1:n]) ** m * u[0]")
