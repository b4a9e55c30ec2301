"""The documentation is tested: the generated reference pages equal what the code generates, every
``symkf.`` name the README, the guides and the docstrings mention exists, every Python code block
of the README and the guides runs, and the site builds with warnings as errors (when MkDocs is
installed)."""
import importlib
import inspect
import os
import pkgutil
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from symkf.scenarios.cli_reference import families_markdown, options_markdown

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
ROOMS = ("models", "codegen", "runtime", "scenarios")
#: The pages whose Python blocks run, in this order, in one folder (later pages use earlier files).
RUN_ORDER = ("docs/getting-started.md", "README.md", "docs/guide/model-authoring.md", "docs/guide/filter-api.md",
             "docs/guide/campaigns.md", "docs/guide/smoothing.md")
ROLE = re.compile(r":(func|class|meth|data|mod|attr):`~?([\w.]+)`")
DOTTED = re.compile(r"\bsymkf(?:\.\w+)+")

pytestmark = pytest.mark.skipif(not (DOCS / "index.md").is_file(), reason="needs the source checkout's docs/")


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def _resolve(name: str, *namespaces) -> bool:
    """True if the dotted ``name`` is an importable module or an attribute reachable from one of
    ``namespaces`` (modules or classes) or, for a ``symkf.`` name, from its module."""
    parts = name.split(".")
    if parts[0] == "symkf":
        for i in range(len(parts), 1, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ImportError:
                continue
            return _walk(obj, parts[i:])
        return False
    return any(_walk(space, parts) for space in namespaces if space is not None)


def _walk(obj, parts) -> bool:
    for part in parts:
        if not hasattr(obj, part):
            return False
        obj = getattr(obj, part)
    return True


def _modules() -> list:
    found = []
    for room in ROOMS:
        package = importlib.import_module(f"symkf.{room}")
        found.append(package)
        found += [importlib.import_module(info.name)
                  for info in pkgutil.walk_packages(package.__path__, f"symkf.{room}.")]
    return found


def test_the_codegen_options_page_is_generated_from_the_declarations():
    assert (DOCS / "reference" / "codegen-options.md").read_text(encoding="utf-8") == options_markdown(), \
        "regenerate it: symkf options --markdown > docs/reference/codegen-options.md"


def test_the_family_table_is_the_one_the_code_lists():
    assert families_markdown() in (DOCS / "guide" / "filters.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_symkf_name_a_page_mentions_exists(page):
    text = page.read_text(encoding="utf-8")
    missing = sorted({name for name in DOTTED.findall(text) if not _resolve(name)})
    assert not missing, f"{page.name} names {missing}, which do not exist"


#: Classes whose members the pages name as ``Class.member``.
CLASSES = {"Model": "symkf.models.base", "Filter": "symkf.runtime.filters", "CompiledModel": "symkf.runtime",
           "RunResult": "symkf.runtime.runs", "CodegenConfig": "symkf.codegen.spec", "Campaign":
           "symkf.scenarios.launcher.campaign"}


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_class_member_a_page_mentions_exists(page):
    text, missing = page.read_text(encoding="utf-8"), []
    for cls_name, member in re.findall(rf"\b({'|'.join(CLASSES)})\.(\w+)", text):
        cls = getattr(importlib.import_module(CLASSES[cls_name]), cls_name)
        if not (hasattr(cls, member) or member in getattr(cls, "__dataclass_fields__", {})):
            missing.append(f"{cls_name}.{member}")
    assert not missing, f"{page.name} names {sorted(set(missing))}, which do not exist"


def test_every_name_a_docstring_refers_to_exists():
    """``:func:`x```, ``:class:`x``` ... in every docstring of the package resolve: absolute
    (``symkf.``), relative to the package (``.module``), in the module or class, or as a class or
    module of the package named by its last name (``Model.measurement`` from a module that does
    not import Model); for ``:attr:`Class.name``` (often an instance attribute) the class."""
    modules = _modules()
    by_name = {}
    for module in modules:
        by_name.setdefault(module.__name__.rpartition(".")[2], module)
        for value in vars(module).values():
            if inspect.isclass(value) and value.__module__.startswith("symkf."):
                by_name.setdefault(value.__name__, value)
    broken = []
    for module in modules:
        package = module.__name__ if hasattr(module, "__path__") else module.__name__.rpartition(".")[0]
        owned = [(module.__doc__, None)]
        for value in vars(module).values():
            if getattr(value, "__module__", None) == module.__name__:
                owned.append((getattr(value, "__doc__", None), value if inspect.isclass(value) else None))
                if inspect.isclass(value):
                    owned += [(getattr(member, "__doc__", None), value) for member in vars(value).values()]
        for doc, owner in owned:
            for role, name in ROLE.findall(doc) if isinstance(doc, str) else ():
                if name.startswith("."):
                    name = package + name
                if role == "attr" and "." in name:         # an instance attribute: its class must exist
                    name = name.rpartition(".")[0]
                elif role == "attr" and owner is not None and f"self.{name} =" in inspect.getsource(owner):
                    continue
                first = by_name.get(name.split(".")[0])
                if not (_resolve(name, owner, module) or (first is not None and _walk(first, name.split(".")[1:]))):
                    broken.append(f"{module.__name__}: {name}")
    assert not broken, f"docstrings name what does not exist: {sorted(set(broken))}"


def _blocks(page: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", page.read_text(encoding="utf-8"), flags=re.M | re.S)


def _run_pages(folder: Path, slow: bool) -> int:
    """Run every Python block of RUN_ORDER's pages in ``folder``; ``# file: NAME`` blocks are
    written to NAME, ``# not run`` blocks skipped, ``# slow`` blocks run only when ``slow``."""
    ran = 0
    for relative in RUN_ORDER:
        namespace = {"__name__": "__docs__"}
        for block in _blocks(ROOT / relative):
            first = block.splitlines()[0]
            if first.startswith("# file: "):
                (folder / first.removeprefix("# file: ").strip()).write_text(block, encoding="utf-8")
            elif first.startswith("# not run") or (first.startswith("# slow") and not slow):
                continue
            else:
                exec(compile(block, f"{relative} block", "exec"), namespace)
                ran += 1
    return ran


def test_every_python_block_of_the_readme_and_guides_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert _run_pages(tmp_path, slow=False) >= 4
    out = capsys.readouterr().out
    assert "t = 10.0 x = [905.08 547.51  -9.9    4.92]" in out          # the output the pages print


@pytest.mark.slow
def test_the_slow_python_blocks_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert _run_pages(tmp_path, slow=True) >= 5


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    if shutil.which("mkdocs") is None and importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install 'symkf[docs]')")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "site" / "reference" / "api" / "runtime" / "index.html").stat().st_size > 20_000


#: A commit hash: 7-40 hex digits with a letter and a digit, not part of a number (7.292115e-5).
COMMIT = re.compile(r"(?<![\w.])(?<!hash )(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}(?![\w.+-])")


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_pages_speak_to_users_not_of_the_history(page):
    text = page.read_text(encoding="utf-8")
    assert not re.search(r"\bissues? \d", text), "an issue number"
    assert not COMMIT.search(text), f"a commit hash: {COMMIT.search(text).group()}"


def test_the_readme_is_a_user_guide():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 210
    assert not re.search(r"issue \d|/work/|shared/data|\.\./", text)
    for needed in ("Python 3.11", "C99 compiler", "Linux", "symkf compare launcher", "python -m pytest",
                   "https://github.com/dlaidig/broad", "MIT"):
        assert needed in text, needed
