"""The stubs `_core.pyi` against the compiled module: every name they
declare exists, every public name of the module is declared, and the
parameters of each function and method match the runtime signatures."""

from __future__ import annotations

import ast
import inspect
import pathlib

import bayes_cbf._core as core

STUB = pathlib.Path(core.__file__).with_name("_core.pyi")


def stub_tree():
    return ast.parse(STUB.read_text())


def params(fn: ast.FunctionDef) -> list[str]:
    a = fn.args
    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
    return [n for n in names if n not in ("self", "cls")]


def runtime_params(obj) -> list[str] | None:
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return None
    return [n for n in sig.parameters if n not in ("self", "cls", "$self")]


def test_every_stub_name_exists_and_every_public_name_has_a_stub():
    tree = stub_tree()
    declared = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            declared.add(node.name)
            assert hasattr(core, node.name), f"{node.name} is in the stub only"
    public = {
        n for n in dir(core)
        if not n.startswith("__") and (callable(getattr(core, n)))
    }
    assert public - declared == set(), f"no stub for {sorted(public - declared)}"


def test_signatures_match():
    checked = 0
    for node in stub_tree().body:
        if isinstance(node, ast.FunctionDef):
            got = runtime_params(getattr(core, node.name))
            if got is not None:
                assert got == params(node), f"{node.name}: runtime {got}, stub {params(node)}"
                checked += 1
        if isinstance(node, ast.ClassDef) and isinstance(getattr(core, node.name), type):
            cls = getattr(core, node.name)
            for item in node.body:
                if not isinstance(item, ast.FunctionDef):
                    continue
                assert hasattr(cls, item.name), f"{node.name}.{item.name} is in the stub only"
                if item.name.startswith("__") or any(
                    isinstance(d, ast.Name) and d.id == "property" for d in item.decorator_list
                ):
                    continue
                got = runtime_params(getattr(cls, item.name))
                if got is not None:
                    assert got == params(item), (
                        f"{node.name}.{item.name}: runtime {got}, stub {params(item)}"
                    )
                    checked += 1
    assert checked >= 30, checked


def test_runtime_signatures_show_the_stub_defaults():
    sig = inspect.signature(core.MVGP.fit)
    assert sig.parameters["rank_a"].default == "full"
    assert sig.parameters["rank_b"].default == "full"
    assert inspect.signature(core.CoGP.fit).parameters["rank_s"].default == "full"
