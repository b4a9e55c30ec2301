"""symkf: vehicle models written once in CasADi, generated into C filters, run from Python.

    symkf build <model> [--force] [--out DIR] [--set KEY=VALUE ...]
                                        generate + compile a model (cached by a hash of what is
                                        generated); <model>: launcher, attitude, geo_satellite,
                                        marg, path/to/tracker.py or mypkg.tracker
    symkf compare <name> [options]      run a paper's experiment (symkf compare --help lists them)
    symkf bench <name> [options]        a timing table (symkf bench --help lists them)
    symkf options [--markdown]          every codegen option for --set, with type, default and meaning
    symkf families                      the filter families a model can ask for, and what x0, P0, Q mean
    symkf plot <folder> [--out DIR]     redraw a saved comparison's figures from its series.nc (no filter runs)
    symkf design-guidance               re-solve the launcher guidance (IPOPT)
    symkf --version                     the installed symkf (and CasADi) version

"""
from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import json
import pkgutil
import re
import sys
import textwrap
import warnings
from pathlib import Path

from symkf.codegen import BuildError, BundleRepairWarning, build_model, export_bundle
from symkf.codegen.spec import ConfigError
from symkf.models import ModelError
from symkf.scenarios import cli_reference


#: What a user calls the modules of each command.
WHAT = {"compare": "experiment", "bench": "bench"}


def entries(kind: str) -> dict[str, str]:
    """{name: module} of every ``kind`` ("compare" or "bench") in the installed ``symkf.scenarios``:
    a module ``compare`` / ``bench`` of a sub-package (named after the sub-package), or a module
    ``<name>_compare`` / ``<name>_bench`` (named ``<name>``). Each defines ``add_arguments(parser)``
    and ``run(args) -> int``; its docstring's first paragraph is its description."""
    scenarios = importlib.import_module("symkf.scenarios")
    found = {}
    for info in pkgutil.walk_packages(scenarios.__path__, "symkf.scenarios."):
        parent, _, leaf = info.name.rpartition(".")
        if info.ispkg:
            continue
        if leaf == kind and parent != "symkf.scenarios":
            found[parent.rpartition(".")[2]] = info.name
        elif leaf.endswith(f"_{kind}"):
            found[leaf[:-len(kind) - 1]] = info.name
    return dict(sorted(found.items()))


def description(module: str) -> str:
    """The first paragraph of a module's docstring, on one line (read from its source, not imported)."""
    origin = importlib.util.find_spec(module).origin
    doc = ast.get_docstring(ast.parse(Path(origin).read_text(encoding="utf-8"))) or ""
    return " ".join(doc.split("\n\n")[0].split())


def _listing(kind: str) -> str:
    """The ``symkf <kind> --help`` text: usage and every name with its description."""
    found = entries(kind)
    width = max(map(len, found), default=0) + 2
    lines = [f"usage: symkf {kind} <name> [options]   (symkf {kind} <name> --help: its options)", "", f"{WHAT[kind]}{'es' if kind == 'bench' else 's'}:"]
    for name, module in found.items():
        lines += textwrap.wrap(description(module), 100, initial_indent=f"  {name:<{width}}",
                               subsequent_indent=" " * (width + 2))
    return "\n".join(lines)


def _plain(doc: str) -> str:
    """A module docstring as help text: without the reStructuredText markup of ``literals`` and
    :role:`targets` (the docstrings also feed the API reference)."""
    return re.sub(r":\w+:`~?([^`]+)`", r"\1", doc).replace("``", "")


def _option(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` with VALUE read as JSON when it parses (numbers), else as a string."""
    key, sep, value = text.partition("=")
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got '{text}'")
    try:
        return key, json.loads(value)
    except ValueError:
        return key, value


def _cmd_build(args) -> int:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BundleRepairWarning)         # said below, on one line
        result = build_model(args.model, force=args.force, **dict(args.set or []))
    if result.repaired:
        print(f"{result.model}: {result.repaired} in {result.directory}; regenerated the bundle")
    if result.up_to_date:
        print(f"{result.model}: up to date ({result.directory}, checked in {result.seconds * 1e3:.0f} ms)")
    else:
        print(f"{result.model}: built {result.directory} in {result.seconds:.1f} s (hash {result.content_hash[:12]})")
    if args.out:
        files = export_bundle(result, args.out)
        print(f"{result.model}: exported {', '.join(f.name for f in files)} to {args.out}")
    return 0


def _cmd_plot(args) -> int:
    from symkf.scenarios import plot
    try:
        paths = plot.redraw(args.folder, args.out)
    except (FileNotFoundError, ValueError) as exc:
        print(f"symkf plot: {exc}", file=sys.stderr)
        return 1
    for path in paths:
        print(f"wrote {path}")
    return 0


def _dispatch(kind: str, argv: list[str]) -> int:
    if argv and argv[0] in ("-h", "--help"):
        print(_listing(kind))
        return 0
    if not argv or argv[0].startswith("-"):
        print(_listing(kind), file=sys.stderr)
        return 2
    name, rest = argv[0], argv[1:]
    found = entries(kind)
    if name not in found:
        print(f"symkf {kind}: no {WHAT[kind]} named '{name}'; choose from: {', '.join(found)}", file=sys.stderr)
        return 2
    module = importlib.import_module(found[name])
    parser = argparse.ArgumentParser(prog=f"symkf {kind} {name}", description=_plain(module.__doc__ or ""),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    return int(module.run(parser.parse_args(rest)) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("compare", "bench"):
        try:
            return _dispatch(argv[0], argv[1:])
        except (BuildError, ConfigError, ModelError) as exc:
            print(f"symkf {argv[0]}: {exc}", file=sys.stderr)
            return 1
    parser = argparse.ArgumentParser(prog="symkf", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=cli_reference.version_text())
    sub = parser.add_subparsers(dest="command", required=True)
    build = sub.add_parser("build", help="generate and compile a model (paper model name, .py file or module)",
                           description="Generate and compile a model (cached by a hash of what is generated).",
                           epilog=cli_reference.models_text(), formatter_class=argparse.RawDescriptionHelpFormatter)
    build.add_argument("model", help="launcher | attitude | geo_satellite | marg | path/to/model.py | package.module")
    build.add_argument("--force", action="store_true", help="rebuild even if up to date")
    build.add_argument("--out", type=Path, help="also export the flight bundle (.c .h Makefile manifest .so) here: only files that "
                       "match their digests, whole or not at all, never over a symlink or another user's file")
    build.add_argument("--set", type=_option, action="append", metavar="KEY=VALUE",
                       help="a codegen option, e.g. rk4_substeps=2 (each configuration has its own folder; "
                            "symkf options lists them)")
    build.set_defaults(handler=_cmd_build)
    sub.add_parser("compare", help="run a paper's experiment: symkf compare --help lists them")
    sub.add_parser("bench", help="a timing table: symkf bench --help lists them")
    options = sub.add_parser("options", help="list every codegen option with its type, default and meaning")
    options.add_argument("--markdown", action="store_true", help="as the documentation's reference table")
    options.set_defaults(handler=lambda a: print(cli_reference.options_markdown(), end="") if a.markdown
                         else print(cli_reference.options_text()))
    families = sub.add_parser("families", help="list the filter families and what x0, P0 and Q mean for each")
    families.set_defaults(handler=lambda a: print(cli_reference.families_text()))
    plot = sub.add_parser("plot", help="redraw the figures of a saved comparison (no filter is run)",
                          description="Redraw the figures of every comparison saved in FOLDER (or one folder down) from "
                                      "the series.nc (or series.npz) that `symkf compare <name>` wrote there: "
                                      "launcher, attitude, geo, marg.")
    plot.add_argument("folder", type=Path, help="a folder written by symkf compare (e.g. results/launcher, results/attitude)")
    plot.add_argument("--out", type=Path, help="where to write the figures (default: FOLDER)")
    plot.set_defaults(handler=_cmd_plot)
    guidance = sub.add_parser("design-guidance", help="re-solve the launcher guidance with IPOPT")
    guidance.set_defaults(handler=lambda a: importlib.import_module("symkf.scenarios.launcher.guidance").main())
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (BuildError, ConfigError, ModelError) as exc:
        print(f"symkf {args.command}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:                    # a fault outside the build folder (e.g. reading the model file)
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"symkf {args.command}: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
