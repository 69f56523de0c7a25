"""The repository speaks of the software: its words, its references and its error tree.

* No words about how the project was developed (ticket numbers, work phases, dated diaries)
  anywhere in the code, tests, benchmarks, scripts, CI or documentation; that history lives in
  ``CHANGELOG.md`` alone.
* Every module path a document or a docstring names (``probegrid.core.sh``,
  ``probegrid.core.sh.project_cube``, ``probegrid/bake/driver.py``, ``tests/test_store.py``)
  exists, so that a reader who follows one finds it.
* ``from probegrid import ProbegridError`` is the base of every error the package defines.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import io
import pkgutil
import re
import tokenize
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
THIS = Path(__file__).resolve()

# ------------------------------------------------------------------------------ process words

#: Files that must not speak of the development process (CHANGELOG.md is the one place for it).
_PROSE_ROOTS = ("README.md", "docs", "probegrid", "service", "tests", "benchmarks", "scripts",
                ".ci/run", "pyproject.toml")
_TEXT_SUFFIXES = {".py", ".md", ".js", ".html", ".css", ".toml", ".json", ".txt", ".cfg", ""}
_SKIP_PARTS = {"vendor", "node_modules", "__pycache__", ".pytest_cache", "build"}

_ORDINALS = ("first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|"
             "twelfth|last|next|final|previous|earlier|later|this|that|each|every")

#: Words that date a text by the project's history rather than describe the software. Precise on
#: purpose: "stops when the estimate settles", "Ctrl-C stops", ``scope="session"`` (pytest's
#: fixture scope) and "stops" of exposure are fine.
PROCESS_PATTERNS: tuple[re.Pattern[str], ...] = tuple(re.compile(p, re.IGNORECASE) for p in (
    r"\bissues?\s*#?\s*\d",                       # a ticket number
    r"\(#\d+\b|\bmerge\s+#\d+",                    # a ticket or pull request number
    r"\bitems?\s+\d+\b",                           # an item of a ticket's list
    rf"\b(?:{_ORDINALS})\s+stop\b",                # a phase of work
    r"\b(?:earlier|previous|later|past|last|next|first|recent)\s+stops\b",
    r"\bstops?'s?\s+(?:code|bake|figures?|work|final)\b",
    r"\bstop's\b",
    r"(?<![\"'])\bsessions?\b(?![\"'])",           # pytest's scope="session" is fine
    r"\bbake\s+v\d\b|\bpre-v\d\b|\bv\d\s+as\s+first\s+landed\b",
    r"\bwip/",                                      # work-in-progress branch names
    r"\bthe\s+issue'?s\b",                           # "the target"
    r"\buntil\s+the\s+\w+\s+stop\b",
))


def _prose_files() -> Iterator[Path]:
    for name in _PROSE_ROOTS:
        path = ROOT / name
        if path.is_file():
            yield path
        elif path.is_dir():
            for f in sorted(path.rglob("*")):
                if (f.is_file() and f.suffix in _TEXT_SUFFIXES and f.resolve() != THIS
                        and not _SKIP_PARTS.intersection(f.relative_to(ROOT).parts)
                        and f.name != "package-lock.json"):
                    yield f


def test_no_development_process_words() -> None:
    """Code, tests and documents say what the software does and why, not when or in which piece
    of work it changed (CHANGELOG.md keeps the history)."""
    hits = []
    for f in _prose_files():
        try:
            text = f.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            for pattern in PROCESS_PATTERNS:
                m = pattern.search(line)
                if m:
                    hits.append(f"{f.relative_to(ROOT)}:{n}: {m.group(0)!r}: {line.strip()[:100]}")
                    break
    assert not hits, "development-process words:\n" + "\n".join(hits)


def test_process_patterns_are_precise() -> None:
    """The patterns catch the diary and leave ordinary English and pytest's API alone."""
    # (split literals: the examples must not trip the grep of this very file)
    caught = ["iss" "ue 10, it" "em 7", "(#" "9)", "Iss" "ue 14 it" "em 13",
              "this st" "op's final code", "Earlier st" "ops: 0.3", "before bake" " v2",
              "the previous st" "op's bake", "Until the seventh st" "op",
              "as in the last sess" "ion", "wip" "/filter", "next to the iss" "ue's target of 2 s"]
    free = ["Ctrl-C stops", "stops when the Aitken estimate settles", "exposure in stops",
            '@pytest.fixture(scope="session")', "stop the server", "backstop",
            "one item per probe", "the bake stops before its store is finished",
            "the items of a list", "a series that stops changing"]
    for text in caught:
        assert any(p.search(text) for p in PROCESS_PATTERNS), text
    for text in free:
        assert not any(p.search(text) for p in PROCESS_PATTERNS), text


# ------------------------------------------------------------------------------ references

_DOTTED = re.compile(r"(?<![\w./-])probegrid(?:\.[A-Za-z_]\w*)+")
_PATH = re.compile(r"(?<![\w./-])((?:[A-Za-z_][\w-]*/)+[A-Za-z_][\w-]*\.py)\b")
_MOD_ROLE = re.compile(r":mod:`~?([\w.]+)`")
#: A code span of a document that starts with one of the package's modules (`kernels.split_hits`).
_SPAN = re.compile(r"`((?:" + "|".join(sorted(
    {p.stem for p in (ROOT / "probegrid").glob("*.py") if p.stem != "__init__"}
    | {p.name for p in (ROOT / "probegrid").iterdir() if (p / "__init__.py").is_file()}))
    + r")(?:\.[A-Za-z_]\w*)+)(?:\(\))?`")
_FILE_SUFFIXES = {"glb", "gltf", "json", "ktx2", "exr", "hdr", "png", "npy", "py", "md", "bin",
                  "probes", "wesl", "js", "html"}
#: Names that look like module paths but are something else (a store format's name).
_NOT_MODULES = {"probegrid.store.v2", "probegrid.store.v1"}


def _source_text(path: Path) -> str:
    """The comments and docstrings (every string statement) of a Python file, each tagged with
    its first line: where a reference is prose. Other string literals are data (a logger's or
    a file format's name, a cache key) and code references are checked by importing the code."""
    source = path.read_text(encoding="utf-8")
    parts = [(tok.start[0], tok.string)
             for tok in tokenize.generate_tokens(io.StringIO(source).readline)
             if tok.type == tokenize.COMMENT]
    parts += [(node.lineno, node.value.value) for node in ast.walk(_tree(path))
              if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
              and isinstance(node.value.value, str)]
    return "\n".join(f"\x00{line}\x00{text}" for line, text in sorted(parts))


def _documents() -> Iterator[tuple[Path, str]]:
    """(file, text) of every document and module whose references must resolve."""
    yield ROOT / "README.md", (ROOT / "README.md").read_text(encoding="utf-8")
    for f in sorted((ROOT / "docs").rglob("*.md")):
        yield f, f.read_text(encoding="utf-8")
    for top in ("probegrid", "service", "benchmarks", "scripts"):
        for f in sorted((ROOT / top).rglob("*.py")):
            if not _SKIP_PARTS.intersection(f.relative_to(ROOT).parts):
                yield f, _source_text(f)


def _line_of(text: str, pos: int) -> int:
    """The file line of a match: the ``\\x00line\\x00`` tag before it (Python sources), else
    the count of newlines (documents)."""
    tag = text.rfind("\x00", 0, pos)
    if tag > 0:
        start = text.rfind("\x00", 0, tag)
        head = text[start + 1:tag]
        if head.isdigit():
            return int(head) + text.count("\n", tag, pos)
    return text.count("\n", 0, pos) + 1


def _module_file(parts: tuple[str, ...]) -> Path | None:
    base = ROOT.joinpath(*parts)
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return None


@cache
def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"))


def _defined_names(body: list[ast.stmt]) -> set[str]:
    """Names a module or class body binds, statically (defs, classes, assignments, imports,
    ``__all__`` and the keys of a lazy-export table)."""
    names: set[str] = set()
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                for sub in ast.walk(t):
                    if isinstance(sub, ast.Name):
                        names.add(sub.id)
            value = node.value
            if isinstance(value, (ast.List, ast.Tuple, ast.Dict)):
                keys = value.keys if isinstance(value, ast.Dict) else value.elts
                names.update(k.value for k in keys
                             if isinstance(k, ast.Constant) and isinstance(k.value, str))
        elif isinstance(node, (ast.If, ast.Try, ast.With)):
            inner = list(node.body)
            inner += getattr(node, "orelse", []) + getattr(node, "finalbody", [])
            for handler in getattr(node, "handlers", []):
                inner += handler.body
            names |= _defined_names(inner)
    return names


def _class_body(body: list[ast.stmt], name: str) -> list[ast.stmt] | None:
    for node in body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return node.body
    return None


def _resolves(dotted: str) -> bool:
    """A module or package file exists for the longest prefix, and the rest names attributes:
    checked statically (ast), else by importing the module."""
    parts = tuple(dotted.split("."))
    for cut in range(len(parts), 0, -1):
        path = _module_file(parts[:cut])
        if path is not None:
            break
    else:
        return False
    rest = parts[cut:]
    if not rest:
        return True
    body: list[ast.stmt] | None = _tree(path).body
    for name in rest:
        if body is None or name not in _defined_names(body):
            break
        body = _class_body(body, name)
    else:
        return True
    try:  # re-exports, lazy attributes, enum members, dataclass fields
        value = importlib.import_module(".".join(parts[:cut]))
        for name in rest:
            value = getattr(value, name)
            if inspect.ismodule(value) and name != rest[-1]:
                return False  # a module named by an alias (probegrid.sh): name its real path
    except Exception:
        return False
    return True


def _path_resolves(ref: str, where: Path) -> bool:
    roots = (ROOT, ROOT / "probegrid", where.parent, ROOT / "service")
    return any((root / ref).is_file() for root in roots)


def _stale_references() -> list[str]:
    stale = []
    for f, text in _documents():
        rel = f.relative_to(ROOT)
        for m in _DOTTED.finditer(text):
            ref = m.group(0)
            if ref not in _NOT_MODULES and not _resolves(ref):
                stale.append(f"{rel}:{_line_of(text, m.start())}: {ref}")
        for m in _MOD_ROLE.finditer(text):
            ref = m.group(1)
            package = ".".join(rel.with_suffix("").parts[:-1])
            candidates = [ref, f"probegrid.{ref}", f"{package}.{ref}"]
            if not any(_module_file(tuple(c.split("."))) for c in candidates):
                stale.append(f"{rel}:{_line_of(text, m.start())}: {ref}")
        if f.suffix == ".md":
            for m in _SPAN.finditer(text):
                ref = m.group(1)
                last = ref.rsplit(".", 1)[1]
                if last in _FILE_SUFFIXES or re.match(r"[a-z]+[A-Z]", last):
                    continue  # a file name (scene.glb) or another API (scene.environmentTexture)
                if not _resolves(f"probegrid.{ref}"):
                    stale.append(f"{rel}:{_line_of(text, m.start())}: {ref}")
        for m in _PATH.finditer(text):
            ref = m.group(1)
            if not _path_resolves(ref, f):
                stale.append(f"{rel}:{_line_of(text, m.start())}: {ref}")
    return stale


def test_module_references_resolve() -> None:
    """Every ``probegrid.x.y`` and ``x/y.py`` a document or docstring names exists."""
    stale = _stale_references()
    assert not stale, "references to modules, files or names that do not exist:\n" + "\n".join(
        stale)


# ------------------------------------------------------------------------------ the error tree

def test_probegrid_error_is_exported() -> None:
    import probegrid
    from probegrid import ProbegridError
    from probegrid.errors import ProbegridError as base

    assert ProbegridError is base
    assert "ProbegridError" in probegrid.__all__


def _package_modules() -> Iterator[str]:
    import probegrid

    for info in pkgutil.walk_packages(probegrid.__path__, "probegrid."):
        yield info.name


def test_every_package_error_is_a_probegrid_error() -> None:
    """Every exception class the package defines derives from :class:`ProbegridError`, so
    ``except ProbegridError`` catches whatever probegrid raises on purpose."""
    from probegrid import ProbegridError

    outside = []
    for name in _package_modules():
        path = _module_file(tuple(name.split(".")))
        if path is None or "Error" not in path.read_text(encoding="utf-8"):
            continue
        classes = [n.name for n in ast.walk(_tree(path)) if isinstance(n, ast.ClassDef)]
        if not classes:
            continue
        module = importlib.import_module(name)
        for cls_name in classes:
            cls = getattr(module, cls_name, None)
            if (inspect.isclass(cls) and issubclass(cls, BaseException)
                    and cls.__module__ == name and not issubclass(cls, ProbegridError)):
                outside.append(f"{name}.{cls_name}")
    assert not outside, f"errors outside the ProbegridError tree: {outside}"


@pytest.mark.parametrize("name", ["SceneError", "StoreError", "ImageError", "SettingsError",
                                  "ExecutorError"])
def test_error_tree_keeps_its_builtin_bases(name: str) -> None:
    from probegrid import ProbegridError, errors

    cls = getattr(errors, name)
    assert issubclass(cls, ProbegridError)
    assert issubclass(cls, ValueError) or issubclass(cls, RuntimeError)


# ------------------------------------------------------------------------------ commands shown
#: A command as the documents show it in a code span or block: ``probegrid CMD ...`` or, in a
#: span, ``CMD ARG ...`` for the commands that take a file first.
_COMMAND_SPAN = re.compile(
    r"(?:probegrid\s+|^)(filter|bake|export|info|serve|demo)\s([^`\n|;&]*)")


def _shown_commands() -> Iterator[tuple[Path, str, str]]:
    """(document, command, the rest of its line) of every command line the documents show."""
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    for doc in docs:
        text = doc.read_text(encoding="utf-8")
        spans = re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S)
        spans = [ln for block in spans for ln in block.splitlines()]
        spans += re.findall(r"(?<!`)`([^`\n]+)`(?!`)", re.sub(r"```.*?```", "", text,
                                                                flags=re.S))
        for span in spans:
            for m in _COMMAND_SPAN.finditer(span.strip()):
                yield doc, m.group(1), m.group(2)


def test_every_option_a_document_shows_with_a_command_is_one_of_its_options() -> None:
    from probegrid.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    flags = {name: {s for a in sub._actions for s in a.option_strings}
             for name, sub in commands.items()}
    shown = list(_shown_commands())
    assert len(shown) > 10  # (the pattern finds the documents' commands)
    wrong = [(doc.name, cmd, opt) for doc, cmd, rest in shown
             for opt in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", rest)
             if opt not in flags[cmd]]
    assert not wrong


def test_the_threejs_snippet_makes_a_ktx2_loader_that_can_load() -> None:
    """three's KTX2Loader throws on load until detectSupport(renderer) has run."""
    text = (ROOT / "docs" / "engines.md").read_text(encoding="utf-8")
    snippet = re.search(r"```js\n(.*?)```", text, flags=re.S)
    assert snippet is not None
    code = snippet.group(1)
    made = code.find("new KTX2Loader().detectSupport(renderer)")
    assert 0 <= made < code.find("ktx2Loader.loadAsync")
