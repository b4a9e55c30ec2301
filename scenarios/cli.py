"""The ``symkf`` command line.

    symkf build <model> [--force]       generate + compile build/<model>/ (content-hash cached)
    symkf compare <name> [options]      a paper's experiment (scenarios/<name>/compare.py)
    symkf bench <name> [--json]         timing table (scenarios/<name>/bench.py)
    symkf design-guidance               re-solve the launcher guidance (IPOPT)

``compare`` and ``bench`` find their scenario by module name, so a new experiment is a new folder
``scenarios/<name>/`` whose ``compare.py`` / ``bench.py`` define ``add_arguments(parser)`` and
``run(args) -> int``.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from symkf.codegen import BuildError, build_model
from symkf.models import ModelError


def _scenario_module(kind: str, name: str):
    if not name.isidentifier():
        return None
    try:
        return importlib.import_module(f"symkf.scenarios.{name}.{kind}")
    except ModuleNotFoundError as exc:
        if exc.name in (f"symkf.scenarios.{name}", f"symkf.scenarios.{name}.{kind}"):
            return None
        raise


def _cmd_build(args) -> int:
    result = build_model(args.model, force=args.force)
    if result.up_to_date:
        print(f"{args.model}: up to date ({result.directory}, checked in {result.seconds * 1e3:.0f} ms)")
    else:
        print(f"{args.model}: built {result.directory} in {result.seconds:.1f} s (hash {result.content_hash[:12]})")
    return 0


def _dispatch(kind: str, argv: list[str]) -> int:
    if not argv or argv[0].startswith("-"):
        print(f"usage: symkf {kind} <name> [options]", file=sys.stderr)
        return 2
    name, rest = argv[0], argv[1:]
    module = _scenario_module(kind, name)
    if module is None:
        print(f"symkf {kind}: no scenario '{name}' (expected scenarios/{name}/{kind}.py)", file=sys.stderr)
        return 2
    parser = argparse.ArgumentParser(prog=f"symkf {kind} {name}", description=module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    return int(module.run(parser.parse_args(rest)) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("compare", "bench"):
        try:
            return _dispatch(argv[0], argv[1:])
        except (BuildError, ModelError) as exc:
            print(f"symkf {argv[0]}: {exc}", file=sys.stderr)
            return 1
    parser = argparse.ArgumentParser(prog="symkf", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    build = sub.add_parser("build", help="generate and compile build/<model>/")
    build.add_argument("model")
    build.add_argument("--force", action="store_true", help="rebuild even if up to date")
    build.set_defaults(handler=_cmd_build)
    sub.add_parser("compare", help="run a paper's experiment: symkf compare <name> --help")
    sub.add_parser("bench", help="timing table: symkf bench <name> --help")
    guidance = sub.add_parser("design-guidance", help="re-solve the launcher guidance with IPOPT")
    guidance.set_defaults(handler=lambda a: importlib.import_module("symkf.scenarios.launcher.guidance").main())
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (BuildError, ModelError) as exc:
        print(f"symkf {args.command}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
