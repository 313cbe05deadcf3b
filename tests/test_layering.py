"""The library sits below the application: no module of ``falcon_plan`` imports the
``service`` package (read from the source with ast, so a lazy import inside a function counts
too); the service's subcommands reach the one command line through the entry-point group."""
from __future__ import annotations

import ast
from pathlib import Path

import falcon_plan
from falcon_plan import cli

APPLICATION = "service"


def _imported_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every import statement and importlib.import_module("...") call."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
        elif (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None))
              in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)):
            found.append((node.lineno, node.args[0].value))
    return found


def _imports_application(module: str) -> bool:
    return module == APPLICATION or module.startswith(APPLICATION + ".")


def test_the_library_imports_nothing_from_the_service() -> None:
    root = Path(falcon_plan.__file__).parent
    sources = sorted(root.rglob("*.py"))
    assert len(sources) > 50
    offending = [f"{path.relative_to(root.parent)}:{line}: {module}"
                 for path in sources for line, module in _imported_modules(ast.parse(path.read_text(), str(path)))
                 if _imports_application(module)]
    assert not offending, "falcon_plan must not import the service package:\n" + "\n".join(offending)


def test_the_scan_sees_every_form_of_import() -> None:
    tree = ast.parse("import service\nfrom service.config import x\ndef f():\n    import service.keys as k\n"
                     "import importlib\nimportlib.import_module('service.main')\nfrom servicex import y\n"
                     "from . import service\n")
    assert [m for _, m in _imported_modules(tree) if _imports_application(m)] == [
        "service", "service.config", "service.keys", "service.main"]


def test_the_service_commands_are_plugged_into_the_one_command_line() -> None:
    names = cli.command_names()
    assert {"serve", "request", "demo", "router"} <= set(names)
    assert len(names) == len(set(names))
    choices = cli.build_parser()._subparsers._group_actions[0].choices
    assert set(choices) == set(names)
    assert {entry.value.split(":")[0] for entry in cli.plugin_commands()} >= {
        "service.commands.serve", "service.commands.request", "service.commands.demo", "service.commands.router"}
