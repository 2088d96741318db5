"""The documentation: every Python block of README.md and docs/*.md names things that exist, the
short ones run, links stay inside the repository, and the README stays a user's page.

A block runs when the line before its fence is ``<!-- docs-test: run -->`` (short, no data).
The others need a scene folder or a service; their imports, ``sparseart.*`` names, call keywords and
the attributes they read on results are checked without running them.
"""
from __future__ import annotations

import ast
import importlib
import inspect
import os
import re
import types
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINKED = [*DOCS, REPO / "CHANGELOG.md", REPO / "benchmarks" / "EXPERIMENTS.md",
          REPO / "benchmarks" / "results" / "current" / "README.md"]
RUN_MARK = "<!-- docs-test: run -->"
README_MAX_LINES = 250
CI_TEST_LINE = "bash scripts/setup.sh && python3 -m pytest -q -n 2"
DOC_PAGES = ["input", "output", "how-it-works", "registration", "models", "benchmarks", "limits", "development"]


@dataclass
class Block:
    path: Path
    line: int          # 1-based line of the opening fence
    source: str
    run: bool

    @property
    def id(self) -> str:
        return f"{self.path.relative_to(REPO)}:{self.line}"


def python_blocks(path: Path) -> list[Block]:
    """The ```python blocks of a Markdown file, each marked to run or not."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        if lines[i].strip() == "```python":
            previous = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
            end = next(j for j in range(i + 1, len(lines)) if lines[j].strip() == "```")
            blocks.append(Block(path, i + 1, "\n".join(lines[i + 1:end]) + "\n", previous == RUN_MARK))
            i = end
        i += 1
    return blocks


BLOCKS = [b for path in DOCS for b in python_blocks(path)]


def _result_types() -> list[type]:
    """The public objects a user's code reads attributes of (results, their parts and clouds)."""
    import sparseart
    from sparseart.types import StageRecord

    return [sparseart.Articulation, sparseart.PartResult, sparseart.PartSpec, sparseart.JointEstimate,
            sparseart.PartLabels, sparseart.LabelledCloud, sparseart.Scene, sparseart.Frame, sparseart.Camera,
            sparseart.RunOptions, StageRecord]


def _resolve(module_name: str, attributes: list[str]):
    """module_name.attr1.attr2... -> the object, importing submodules on the way. Raises on a missing name."""
    obj = importlib.import_module(module_name)
    path = module_name
    for name in attributes:
        path = f"{path}.{name}"
        if hasattr(obj, name):
            obj = getattr(obj, name)
        elif isinstance(obj, types.ModuleType):
            obj = importlib.import_module(path)     # a submodule not imported by its package
        else:
            raise AttributeError(f"{path} does not exist")
    return obj


def _chain(node: ast.AST) -> tuple[str, list[str]] | None:
    """``a.b.c`` -> ("a", ["b", "c"]); None when the chain does not start at a plain name."""
    names = []
    while isinstance(node, ast.Attribute):
        names.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        return node.id, names[::-1]
    return None


def problems(source: str) -> list[str]:
    """What a Python block names that does not exist (empty list: all fine).

    Checks every import, every attribute chain on an imported module (``sparseart.run``,
    ``sparseart.io.urdf.write_urdf``), the keywords and positional count of calls to resolved
    callables (for ``sparseart.run``/``run_clouds`` the extra keywords must be RunOptions fields),
    and, in blocks that are not run, that attributes read on other names exist on a result type.
    """
    found: list[str] = []
    try:
        tree = ast.parse(source)
    except SyntaxError as error:
        return [f"syntax error: {error}"]
    modules: dict[str, str] = {}        # local name -> module path
    objects: dict[str, object] = {}     # local name -> object imported by name
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                try:
                    importlib.import_module(alias.name)
                except ImportError as error:
                    found.append(f"import {alias.name}: {error}")
                    continue
                if alias.asname:
                    modules[alias.asname] = alias.name
                else:
                    modules[alias.name.split(".")[0]] = alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            if node.level or not node.module:
                found.append("relative import")
                continue
            for alias in node.names:
                try:
                    obj = _resolve(node.module, [alias.name])
                except (ImportError, AttributeError) as error:
                    found.append(f"from {node.module} import {alias.name}: {error}")
                    continue
                local = alias.asname or alias.name
                if isinstance(obj, types.ModuleType):
                    modules[local] = obj.__name__
                else:
                    objects[local] = obj
    resolved: dict[int, object] = {}    # id(ast node) -> object, for the call checks
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and not isinstance(getattr(node, "_parent", None), ast.Attribute):
            chain = _chain(node)
            if chain and chain[0] in modules:
                try:
                    resolved[id(node)] = _resolve(modules[chain[0]], chain[1])
                except (ImportError, AttributeError) as error:
                    found.append(f"{chain[0]}.{'.'.join(chain[1])}: {error}")
        elif isinstance(node, ast.Name) and node.id in objects:
            resolved[id(node)] = objects[node.id]
        for child in ast.iter_child_nodes(node):
            child._parent = node  # type: ignore[attr-defined]
    found.extend(_call_problems(tree, resolved))
    return found


def _call_problems(tree: ast.AST, resolved: dict[int, object]) -> list[str]:
    import sparseart

    found = []
    option_fields = {f.name for f in fields(sparseart.RunOptions)}
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call) or id(node.func) not in resolved:
            continue
        function = resolved[id(node.func)]
        if not callable(function) or any(isinstance(a, ast.Starred) for a in node.args) \
                or any(k.arg is None for k in node.keywords):
            continue
        try:
            signature = inspect.signature(function)
        except (TypeError, ValueError):
            continue
        name = getattr(function, "__qualname__", repr(function))
        try:
            bound = signature.bind(*range(len(node.args)), **{k.arg: None for k in node.keywords})
        except TypeError as error:
            found.append(f"call of {name}: {error}")
            continue
        if function in (sparseart.run, sparseart.run_clouds):
            extra = set(bound.arguments.get("overrides", {})) - option_fields
            if extra:
                found.append(f"call of {name}: {sorted(extra)} are not RunOptions fields")
    return found


def attribute_problems(source: str) -> list[str]:
    """Attributes read on plain variables (``result.joints``, ``joint.axis``) that no result type has."""
    tree = ast.parse(source)
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            imported.update((a.asname or a.name).split(".")[0] for a in node.names)
    known = set()
    for kind in _result_types():
        known.update(dir(kind))
        if is_dataclass(kind):
            known.update(f.name for f in fields(kind))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, (ast.Name, ast.Attribute)):
            chain = _chain(node)
            if chain and chain[0] not in imported and node.attr not in known:
                found.append(f"{node.attr} (read on {chain[0]}) is no attribute of a result type")
    return found


# ---------------------------------------------------------------------------------------------


def test_every_doc_page_and_its_python_blocks_are_found() -> None:
    for page in DOC_PAGES:
        assert (REPO / "docs" / f"{page}.md").is_file(), page
    assert (REPO / "LICENSE").is_file() and "Apache License" in (REPO / "LICENSE").read_text()
    assert (REPO / "CHANGELOG.md").is_file()
    assert len(BLOCKS) >= 4 and any(b.run for b in BLOCKS)
    assert any(b.path.name == "README.md" for b in BLOCKS)


@pytest.mark.parametrize("block", BLOCKS, ids=lambda b: b.id)
def test_python_block_names_exist(block: Block) -> None:
    found = problems(block.source)
    if not block.run:
        found += attribute_problems(block.source)
    assert not found, f"{block.id}: " + "; ".join(found)


@pytest.mark.parametrize("block", [b for b in BLOCKS if b.run], ids=lambda b: b.id)
def test_short_python_block_runs(block: Block, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    exec(compile(block.source, block.id, "exec"), {"__name__": "__docs__"})


@pytest.mark.parametrize("block", [b for b in BLOCKS if not b.run], ids=lambda b: b.id)
def test_blocks_not_run_need_data(block: Block) -> None:
    """A block that is not run must say why: it reads a scene folder or asks a service."""
    assert '"scene/"' in block.source, f"{block.id}: mark it {RUN_MARK!r} or give it a scene folder"
    pytest.skip(f"{block.id} needs a scene folder ('scene/'); its names are checked, it is not run")


def test_checker_catches_what_does_not_exist() -> None:
    assert problems("import sparseart.urdf_export\n")
    assert problems("from sparseart.viz import write_report\n")
    assert problems("import sparseart\nsparseart.no_such_function()\n")
    assert problems("from sparseart.io.urdf import write_urdf\nwrite_urdf(1, 2, nmae='x')\n")
    assert problems("import sparseart\nsparseart.run('scene/', no_such_option=1)\n")
    assert attribute_problems("import sparseart\nr = sparseart.run('s')\nr.no_such_field\n")
    assert not problems("import sparseart\nsparseart.run('scene/', use_masks=False)\n")
    assert not problems("from sparseart.io.ply import write_labelled_clouds\n")


# ---------------------------------------------------------------------------------------------

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
PRIVATE_HOST = re.compile(r"^https?://(localhost|127\.|0\.0\.0\.0|10\.|192\.168\.|\[?::1)", re.I)


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    return {_slug(m.group(1)) for m in re.finditer(r"^#+\s+(.*)$", text, flags=re.M)}


def link_problems(path: Path, text: str | None = None) -> list[str]:
    """Links of a Markdown page (``text``: its content, read from ``path`` when None) that leave the
    repository other than by http(s) to a public host, name a missing file or a missing heading."""
    text = path.read_text(encoding="utf-8") if text is None else text
    text = re.sub(r"```.*?```", "", text, flags=re.S)   # code is not a link
    found = []
    for match in LINK.finditer(text):
        target = match.group(1)
        if re.match(r"^https?://", target):
            if PRIVATE_HOST.match(target):
                found.append(f"{target}: not a public address")
            continue
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, flags=re.I):
            found.append(f"{target}: only http(s) links leave the repository")
            continue
        file_part, _, anchor = target.partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path.resolve()
        try:
            resolved.relative_to(REPO)
        except ValueError:
            found.append(f"{target}: points outside the repository")
            continue
        if not resolved.exists():
            found.append(f"{target}: no such file")
        elif anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
            found.append(f"{target}: no heading #{anchor}")
    return found


@pytest.mark.parametrize("path", LINKED, ids=lambda p: str(p.relative_to(REPO)))
def test_links_stay_in_the_repository(path: Path) -> None:
    found = link_problems(path)
    assert not found, f"{path.relative_to(REPO)}: " + "; ".join(found)


def test_link_checker_catches_bad_links() -> None:
    page = REPO / "docs" / "_link_probe.md"          # never written: its text is given
    text = ("[a](../../shared/design.md) [b](missing.md) [c](input.md#no-such-heading) "
            "[d](http://localhost:8000/x) [e](input.md#clouds-you-already-have) "
            "[f](https://github.com/facebookresearch/vggt) [g](file:///etc/passwd)\n")
    found = link_problems(page, text)
    assert len(found) == 5, found


def test_readme_is_a_short_users_page() -> None:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= README_MAX_LINES, len(text.splitlines())
    assert CI_TEST_LINE in text, "CI runs the README's test command: keep it verbatim"
    assert "../shared" not in text, "the README sends users outside the repository"
    history = re.findall(r"\bstop \d+|\b20\d\d-\d\d-\d\d\b|\bbefore `[a-z_]+/`", text)
    assert not history, f"history belongs in CHANGELOG.md / benchmarks/EXPERIMENTS.md: {history}"
    assert max(len(line) for line in text.splitlines()) <= 200


def test_no_code_cites_a_results_path() -> None:
    """Code and tests cite an experiment id (benchmarks/EXPERIMENTS.md), not a results folder."""
    ids = set(re.findall(r"EXP-\d{3}", (REPO / "benchmarks" / "EXPERIMENTS.md").read_text(encoding="utf-8")))
    cited = set()
    for path in (REPO / "sparseart").rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "benchmarks/results/" not in text, path
        cited.update(re.findall(r"EXP-\d{3}", text))
    assert cited and cited <= ids, sorted(cited - ids)


def test_results_hold_only_current_tables() -> None:
    results = REPO / "benchmarks" / "results"
    entries = sorted(p.name for p in results.iterdir()) if results.is_dir() else []
    assert entries == ["current"], entries
    assert not [p for p in (results / "current").rglob("*") if p.suffix in (".diff", ".jsonl", ".py", ".sh")]
    assert os.path.isfile(results / "current" / "README.md")
