"""The compiler flags of a bundle and its Makefile (``templates/Makefile.mk``), which builds the
units with the flags the Python library uses (so ``make stack`` reproduces the header's stack figures)."""
from __future__ import annotations

from .names import api_file, generated_notice, hash_file
from .template_util import template_text

STRICT_FLAGS = "-std=c99 -Wall -Wextra -Werror -pedantic"
#: Measures each function's stack frame and call graph while compiling (GCC >= 10).
STACK_FLAGS = "-fstack-usage -fcallgraph-info=su"


def precision_flags(config) -> list[str]:
    """Extra compiler flags of a float build: any implicit promotion to double is an error."""
    return ["-Wdouble-promotion"] if config.precision == "float" else []


def makefile(model: str, optimization: str, sources: list[str], own_flags: dict[str, str] | None = None,
             model_source: str = "") -> str:
    """A Makefile that builds the bundle's units with the same flags as the Python library (so
    ``make stack`` reproduces the header's stack figures); ``own_flags``: units compiled with
    their own -O flags (after $(CFLAGS), so they win)."""
    objects = [f[:-2] + ".o" for f in sources]
    floats = [f[:-2] + "_float.o" for f in sources]
    stacks = [f[:-2] + "_stack.o" for f in sources]
    rules = []
    for source, obj, flt, stk in zip(sources, objects, floats, stacks):
        header = f" {model}.h" if source in (api_file(model), hash_file(model)) else ""
        cflags = "$(CFLAGS)" + (f" {own_flags[source]}" if own_flags and source in own_flags else "")
        rules += [f"{obj}: {source}{header}", f"\t$(CC) {cflags} -fPIC -c -o $@ {source}",
                  f"{flt}: {source}{header}", f"\t$(CC) {cflags} -Wdouble-promotion -DSYMKF_FLOAT -c -o $@ {source}",
                  f"{stk}: {source}{header}", f"\t$(CC) {cflags} -fPIC {STACK_FLAGS} -c -o $@ {source}", ""]
    return template_text("Makefile.mk").format(
        notice=generated_notice(model, model_source), model=model, optimization=optimization,
        strict_flags=STRICT_FLAGS, objects=" ".join(objects), float_objects=" ".join(floats),
        stack_objects=" ".join(stacks), rules="\n".join(rules)) + "\n"
