"""The docs name only code that exists.

Three checks over docs/*.md, README.md and CHANGELOG.md:

(a) Paths. Every ``crchfl_sumo/...`` path written anywhere in the text (a ``.py`` file or a
    folder; prose, tables and code blocks alike) exists in the repository.

(b) Dotted references. Inside inline code spans (single or double backticks, outside fenced code
    blocks), every dotted name such as ``learning.model.build_model`` or
    ``driving.dagger.is_correction(..., inside_junction)`` is checked when it is a reference to
    the package:
    - call parentheses are dropped (only the dotted identifier before them is read);
    - a name whose last part is a file extension (``ledger.jsonl``, ``summary.json``,
      ``reproduce_full.toml``, ...) is a file name, not a reference;
    - a name that starts with ``crchfl_sumo.`` is always checked: its longest importable module
      prefix must exist and every part after it must be an attribute;
    - otherwise it is checked only when its first part is one of the package's subpackages
      (core, sumo, links, vision, data, learning, accounting, planning, federation, driving,
      studies, cli) AND its second part is a module of that subpackage
      (``crchfl_sumo/<subpackage>/<module>.py``). So ``federation.seed`` or ``dagger.every``
      (TOML settings: there is no ``federation/seed.py``) are skipped, while
      ``learning.settings.TrainConfig`` is imported and must have ``TrainConfig``;
    - an attribute part is looked up with ``hasattr`` after ``importlib.import_module``; a
      dataclass field without a default counts as an attribute of its class.

(c) Test files. Every ``tests/....py`` path the docs name exists (the suite moved into
    subfolders: tests/<subpackage>/test_*.py).

A failure lists ``file:line: text (why)`` for each bad reference; fix the doc with the name the
code now uses (grep crchfl_sumo/ and tests/ for it).
"""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "crchfl_sumo"
SUBPACKAGES = (
    "core", "sumo", "links", "vision", "data", "learning",
    "accounting", "planning", "federation", "driving", "studies", "cli",
)
FILE_EXTENSIONS = frozenset((  # a dotted name ending in one of these is a file name, not a reference
    "py", "md", "json", "toml", "csv", "pt", "npz", "png", "mp4", "xml", "h5", "jsonl",
    "txt", "yaml", "yml", "html", "sumocfg", "gz", "zip", "npy", "pkl", "log",
))

# References that failed in docs this change could not edit: (file, text, the current name).
# Listed for whoever mends those docs; the tests do NOT skip them. Remove a line once its doc is fixed.
def _package_dirs() -> dict[str, Path]:
    """Packages that pyproject.toml maps from another folder ([tool.setuptools.package-dir]), e.g.
    crchfl_sumo.scenarios, which ships inside the wheel from the repository's scenarios/."""
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    table = re.search(r"^\[tool\.setuptools\.package-dir\]\n(.*?)(?=^\[|\Z)", text, re.MULTILINE | re.DOTALL)
    mapped = {}
    for name, folder in re.findall(r'^"?([\w.]+)"?\s*=\s*"([^"]*)"', table.group(1) if table else "", re.MULTILINE):
        mapped[name] = ROOT / folder
    return mapped


PACKAGE_DIRS = _package_dirs()


def _source_of(path: str) -> Path:
    """Where a crchfl_sumo/... path of the installed package lives in the repository."""
    for name, folder in PACKAGE_DIRS.items():
        prefix = name.replace(".", "/")
        if path == prefix or path.startswith(prefix + "/"):
            return folder / path[len(prefix):].lstrip("/")
    return ROOT / path


def doc_files() -> list[Path]:
    files = sorted((ROOT / "docs").glob("*.md"))
    files += [ROOT / name for name in ("README.md", "CHANGELOG.md") if (ROOT / name).exists()]
    return files


# ----------------------------------------------------------------------------------- paths

PATH_RE = re.compile(r"(?<![\w./-])crchfl_sumo/[\w./-]*")


def path_references(text: str) -> list[tuple[int, str]]:
    """(line, path) for every crchfl_sumo/... path in the text."""
    found = []
    for match in PATH_RE.finditer(text):
        path = match.group(0).rstrip(".,:;-")
        line = text.count("\n", 0, match.start()) + 1
        found.append((line, path))
    return found


def path_problems(text: str) -> list[tuple[int, str, str]]:
    return [
        (line, path, "no such file or folder")
        for line, path in path_references(text)
        if not _source_of(path).exists()
    ]


TESTS_PATH_RE = re.compile(r"(?<![\w./-])tests/[\w./-]*?\.py\b")


def missing_test_files(text: str) -> list[tuple[int, str, str]]:
    """tests/....py files the text names that do not exist (the suite moved into subfolders)."""
    problems = []
    for match in TESTS_PATH_RE.finditer(text):
        if not (ROOT / match.group(0)).is_file():
            line = text.count("\n", 0, match.start()) + 1
            problems.append((line, match.group(0), "no such test file"))
    return problems


# ------------------------------------------------------------------------ dotted references

FENCE_RE = re.compile(r"^\s*(```|~~~)")
SPAN_RE = re.compile(r"(`+)(.+?)(?<!`)\1(?!`)", re.DOTALL)
DOTTED_RE = re.compile(r"(?<![\w./\\-])[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+")


def _prose_paragraphs(text: str) -> list[tuple[int, str]]:
    """(first line, paragraph) of the text outside fenced code blocks."""
    paragraphs: list[tuple[int, str]] = []
    current: list[str] = []
    start = 0
    in_fence = False
    for number, line in enumerate(text.splitlines(), start=1):
        if FENCE_RE.match(line):
            in_fence = not in_fence
            line = ""
        elif in_fence:
            line = ""
        if line.strip():
            if not current:
                start = number
            current.append(line)
        elif current:
            paragraphs.append((start, "\n".join(current)))
            current = []
    if current:
        paragraphs.append((start, "\n".join(current)))
    return paragraphs


def dotted_references(text: str) -> list[tuple[int, str]]:
    """(line, dotted name) of every dotted name inside an inline code span."""
    found = []
    for start, paragraph in _prose_paragraphs(text):
        for span in SPAN_RE.finditer(paragraph):
            code = span.group(2)
            for match in DOTTED_RE.finditer(code):
                line = start + paragraph.count("\n", 0, span.start(2) + match.start())
                found.append((line, match.group(0)))
    return found


def _is_module(subpackage: str, name: str) -> bool:
    return (PACKAGE / subpackage / f"{name}.py").is_file() or (
        PACKAGE / subpackage / name / "__init__.py"
    ).is_file()


def _has_attribute(obj: object, name: str) -> bool:
    if hasattr(obj, name):
        return True
    if isinstance(obj, type) and dataclasses.is_dataclass(obj):
        return any(field.name == name for field in dataclasses.fields(obj))
    return False


def reference_problem(dotted: str) -> str | None:
    """Why a dotted reference is wrong, or None when it is right or not a package reference."""
    parts = dotted.split(".")
    if parts[-1].lower() in FILE_EXTENSIONS:
        return None  # a file name such as ledger.jsonl
    if parts[0] == "crchfl_sumo":
        for name, folder in PACKAGE_DIRS.items():  # crchfl_sumo.scenarios: a folder of data files
            if dotted == name or dotted.startswith(name + "."):
                inner = dotted[len(name):].lstrip(".").split(".") if dotted != name else []
                target = folder.joinpath(*inner)
                return None if target.exists() or target.with_suffix(".py").exists() else f"no {target}"
        module_parts = ["crchfl_sumo"]
        rest = parts[1:]
        while rest:
            candidate = PACKAGE.joinpath(*module_parts[1:], rest[0])
            if candidate.with_suffix(".py").is_file() or (candidate / "__init__.py").is_file():
                module_parts.append(rest.pop(0))
            else:
                break
    else:
        if parts[0] not in SUBPACKAGES or len(parts) < 2 or not _is_module(parts[0], parts[1]):
            return None  # a config key (federation.seed), another library (torch.load), ...
        module_parts = ["crchfl_sumo", parts[0], parts[1]]
        rest = parts[2:]
    module_name = ".".join(module_parts)
    try:
        obj: object = importlib.import_module(module_name)
    except Exception as error:  # noqa: BLE001 - any import failure is the finding
        return f"cannot import {module_name}: {type(error).__name__}: {error}"
    for index, name in enumerate(rest):
        if not _has_attribute(obj, name):
            owner = ".".join(module_parts + rest[:index])
            return f"{owner} has no attribute {name!r}"
        obj = getattr(obj, name, None)
    return None


def dotted_problems(text: str) -> list[tuple[int, str, str]]:
    problems = []
    for line, dotted in dotted_references(text):
        why = reference_problem(dotted)
        if why is not None:
            problems.append((line, dotted, why))
    return problems


# -------------------------------------------------------------------------------- the tests


def _report(kind: str, problems: list[tuple[str, int, str, str]]) -> str:
    lines = [f"{len(problems)} {kind} in the docs name nothing that exists:"]
    lines += [f"  {name}:{line}: {text} ({why})" for name, line, text, why in problems]
    return "\n".join(lines)


def _relative(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _docs_problems(check) -> list[tuple[str, int, str, str]]:
    """(doc, line, text, why) of every problem ``check`` finds in a doc's text."""
    return [
        (_relative(path), line, text, why)
        for path in doc_files()
        for line, text, why in check(path.read_text(encoding="utf-8"))
    ]


def test_docs_name_existing_package_paths():
    problems = _docs_problems(path_problems)
    assert not problems, _report("paths", problems)


def test_docs_name_existing_test_files():
    problems = _docs_problems(missing_test_files)
    assert not problems, _report("test files", problems)


def test_docs_dotted_references_exist():
    problems = _docs_problems(dotted_problems)
    assert not problems, _report("dotted references", problems)


SCRATCH_DOC = """# A scratch doc

Code: `crchfl_sumo/learning/model.py` and crchfl_sumo/driving/ exist;
crchfl_sumo/learning/no_such_module.py does not. crchfl_sumo/scenarios/town01 ships from scenarios/.

The network is `learning.model.build_model(config, seed)`; `learning.model.no_such_builder()`
is made up, and so is `crchfl_sumo.learning.model.NoSuchClass`.
`learning.settings.TrainConfig.precision` is a field, `learning.settings.TrainConfig.no_such_key`
is not. Tested in tests/learning/test_model.py, not in tests/test_no_such_file.py.

Settings, not code: `federation.seed`, `[dagger] every = 2` as `dagger.every`, `train.precision`;
files: `ledger.jsonl`, `federation_state.pt`, `crchfl_sumo/core`, `data.h5`; other libraries:
`torch.load(..., weights_only=True)`; the built-in scenarios: `crchfl_sumo.scenarios`.

```
learning.model.inside_a_fence_is_not_read
```
"""


def test_the_checks_find_made_up_references():
    paths = path_problems(SCRATCH_DOC)
    assert [(line, path) for line, path, _ in paths] == [(4, "crchfl_sumo/learning/no_such_module.py")]
    tests = missing_test_files(SCRATCH_DOC)
    assert [(line, path) for line, path, _ in tests] == [(9, "tests/test_no_such_file.py")]

    dotted = {text: line for line, text, _ in dotted_problems(SCRATCH_DOC)}
    assert dotted == {
        "learning.model.no_such_builder": 6,
        "crchfl_sumo.learning.model.NoSuchClass": 7,
        "learning.settings.TrainConfig.no_such_key": 8,
    }
    read = {text for _, text in dotted_references(SCRATCH_DOC)}
    assert "learning.model.build_model" in read  # the call's parentheses are not part of it
    assert "learning.model.inside_a_fence_is_not_read" not in read
    for skipped in ("federation.seed", "dagger.every", "ledger.jsonl", "torch.load", "data.h5"):
        assert reference_problem(skipped) is None


def test_a_made_up_reference_in_a_scratch_copy_of_a_doc_fails():
    text = (ROOT / "docs" / "model.md").read_text(encoding="utf-8")
    scratch = text + "\nSee `learning.model.made_up_builder(x)`, crchfl_sumo/learning/made_up.py, tests/made_up.py.\n"
    line = scratch.count("\n")
    assert set(dotted_problems(scratch)) - set(dotted_problems(text)) == {
        (line, "learning.model.made_up_builder", "crchfl_sumo.learning.model has no attribute 'made_up_builder'")
    }
    assert set(path_problems(scratch)) - set(path_problems(text)) == {
        (line, "crchfl_sumo/learning/made_up.py", "no such file or folder")
    }
    assert set(missing_test_files(scratch)) - set(missing_test_files(text)) == {
        (line, "tests/made_up.py", "no such test file")
    }


@pytest.mark.parametrize(
    "good", ["learning.model", "crchfl_sumo.core.atomic.read_latest", "crchfl_sumo", "crchfl_sumo.scenarios"]
)
def test_real_references_pass(good):
    assert reference_problem(good) is None


def test_every_reference_doc_is_at_most_20_kb():
    # a newcomer reads a reference in minutes; dated figures go to the measurements record
    sizes = {p.name: p.stat().st_size for p in (ROOT / "docs").glob("*.md") if p.name != "measurements.md"}
    assert sizes and {name: size for name, size in sizes.items() if size > 20_000} == {}
