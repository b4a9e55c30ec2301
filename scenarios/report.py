"""Writing a benchmark's result: the JSON object to ``--out`` (parents created) and to stdout with
``--json``, else the human table."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable


def emit(result: dict, out: Path | None, json_only: bool, print_table: Callable[[dict], None]) -> None:
    """Write ``result`` as JSON to ``out`` when given; print the JSON (``json_only``) or the table."""
    text = json.dumps(result, indent=1)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    if json_only:
        print(text)
    else:
        print_table(result)
