"""Stack use from the compiler: each function's worst-case stack bytes from GCC's
``-fcallgraph-info=su`` call graphs of the units, and the header's placeholders filled with them."""
from __future__ import annotations

import re

_CI_NODE = re.compile(r'node: \{ title: "([^"]+)" label: "([^"]*)"')
_CI_EDGE = re.compile(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"')
_CI_BYTES = re.compile(r"\\n(\d+) bytes \(([\w,]+)\)")
STACK_PLACEHOLDER = "@SYMKF_STACK:{}@"


def stack_usage(callgraph: str) -> dict[str, int]:
    """Worst-case stack bytes of every function in a GCC ``-fcallgraph-info=su`` file: its own
    frame plus the deepest chain of callees defined in the file (library calls count as 0).

    Calls of the host library's SIMD lanes (``<model>_lanes_*``, c_backend/lanes.py) are left out:
    the figures are the flight bundle's, which compiles the scalar code only.

    Raises ValueError on recursion or an unbounded dynamic frame (neither occurs in generated code).
    """
    frames, calls = {}, {}
    for title, label in _CI_NODE.findall(callgraph):
        match = _CI_BYTES.search(label)
        if match:
            if match.group(2) == "dynamic":
                raise ValueError(f"{title}: unbounded dynamic stack frame")
            frames[title] = int(match.group(1))
    for source_name, target in _CI_EDGE.findall(callgraph):
        if "_lanes_" in target:
            continue
        calls.setdefault(source_name, set()).add(target)
    worst: dict[str, int] = {}

    def depth(name: str, path: tuple[str, ...]) -> int:
        if name in path:
            raise ValueError(f"recursion through {name}")
        if name not in worst:
            callees = [depth(c, path + (name,)) for c in calls.get(name, ())]
            worst[name] = frames.get(name, 0) + max(callees, default=0)
        return worst[name]
    return {name: depth(name, ()) for name in frames}


def fill_stack(header_text: str, figures: dict[str, int] | None) -> str:
    """Replace the header's stack placeholders with measured figures (-1: not measured)."""
    def figure(match: re.Match) -> str:
        return str(figures[match.group(1)]) if figures else "-1"
    return re.sub(STACK_PLACEHOLDER.format(r"(\w+)"), figure, header_text)
