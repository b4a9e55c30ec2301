"""The ``symkf`` command line.

    symkf build <model> [--force] [--out DIR] [--set KEY=VALUE ...]
                                        generate + compile a model (cached by a hash of what is
                                        generated); <model>: launcher, attitude, geo_satellite,
                                        marg, path/to/tracker.py or mypkg.tracker
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
import json
import sys
from pathlib import Path

from symkf.codegen import BuildError, build_model, export_bundle
from symkf.codegen.spec import ConfigError
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
    result = build_model(args.model, force=args.force, **dict(args.set or []))
    if result.up_to_date:
        print(f"{result.model}: up to date ({result.directory}, checked in {result.seconds * 1e3:.0f} ms)")
    else:
        print(f"{result.model}: built {result.directory} in {result.seconds:.1f} s (hash {result.content_hash[:12]})")
    if args.out:
        files = export_bundle(result, args.out)
        print(f"{result.model}: exported {', '.join(f.name for f in files)} to {args.out}")
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
        except (BuildError, ConfigError, ModelError) as exc:
            print(f"symkf {argv[0]}: {exc}", file=sys.stderr)
            return 1
    parser = argparse.ArgumentParser(prog="symkf", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    build = sub.add_parser("build", help="generate and compile a model (paper model name, .py file or module)")
    build.add_argument("model", help="launcher | attitude | geo_satellite | marg | path/to/model.py | package.module")
    build.add_argument("--force", action="store_true", help="rebuild even if up to date")
    build.add_argument("--out", type=Path, help="also copy the flight bundle (.c .h Makefile manifest .so) here")
    build.add_argument("--set", type=_option, action="append", metavar="KEY=VALUE",
                       help="a codegen option, e.g. rk4_substeps=2 (each configuration has its own folder)")
    build.set_defaults(handler=_cmd_build)
    sub.add_parser("compare", help="run a paper's experiment: symkf compare <name> --help")
    sub.add_parser("bench", help="timing table: symkf bench <name> --help")
    guidance = sub.add_parser("design-guidance", help="re-solve the launcher guidance with IPOPT")
    guidance.set_defaults(handler=lambda a: importlib.import_module("symkf.scenarios.launcher.guidance").main())
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (BuildError, ConfigError, ModelError) as exc:
        print(f"symkf {args.command}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
