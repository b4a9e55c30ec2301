"""Passes over CasADi's generated C text, and its split into the blocks a translation unit takes.

:class:`CasadiCode` generates one CasADi code generator's C for a bundle's kernels, runs the text
passes (:func:`_internalise`: no exported reflection functions, helpers static;
:func:`_single_copies`, :func:`_inline_helpers`, :func:`_void_unused_parameters`: code GCC
compiles warning-free at every -O level; :func:`_math_macros` and :func:`_typed_literals`: double
or float math chosen by SYMKF_FLOAT), then splits it into top-level blocks so that each function
becomes a unit with only the helpers it uses (:meth:`CasadiCode.unit`). :func:`math_block`: the
SYMKF_<NAME> macros a text calls.
"""
from __future__ import annotations

import hashlib
import re
from collections import Counter

import casadi as ca

from ..spec import Bundle
from .names import function_symbol

#: libm functions CasADi's code may call, each reached through a SYMKF_<NAME> macro.
MATH_FUNCTIONS = ("sin", "cos", "tan", "asin", "acos", "atan", "atan2", "sinh", "cosh", "tanh", "asinh",
                  "acosh", "atanh", "exp", "log", "log10", "log1p", "expm1", "sqrt", "cbrt", "pow", "fabs",
                  "floor", "ceil", "fmod", "fmin", "fmax", "copysign", "erf", "erfc", "hypot", "round", "trunc")
#: A call of a lower-case name (checked against MATH_FUNCTIONS and the character before it: the
#: regular expression scans a generated file fast, the alternation of 33 names with \b did not).
_LOWER_CALL = re.compile(r"[a-z][a-z0-9]*\(")
_MATH_MACRO = {name: f"SYMKF_{name.upper()}(" for name in MATH_FUNCTIONS}

_PREFIXED = re.compile(r"^#define (\w+) CASADI_PREFIX\((\w+)\)$", flags=re.M)


def plain_names(source: str, prefix: str) -> str:
    """``#define casadi_f0 <prefix>_f0`` instead of CasADi's token-pasting CASADI_PREFIX machinery
    (MISRA C:2012 rule 20.10; its macros would be unused, rule 2.5)."""
    source = _PREFIXED.sub(lambda m: f"#define {m.group(1)} {prefix}_{m.group(2)}", source)
    return _drop_directive_block(source, "#ifdef CASADI_CODEGEN_PREFIX").replace(
        "/* How to prefix internal symbols */\n", "")


def _drop_directive_block(source: str, opening: str) -> str:
    """Remove the preprocessor block that starts with the line ``opening`` (to its #endif)."""
    lines = source.splitlines()
    for start, line in enumerate(lines):
        if line.strip() == opening:
            depth = 0
            for end in range(start, len(lines)):
                word = lines[end].strip().split(" ")[0]
                depth += word in ("#if", "#ifdef", "#ifndef")
                depth -= word == "#endif"
                if depth == 0:
                    return "\n".join(lines[:start] + lines[end + 1:]) + "\n"
    return source


#: A numbered symbol of CasADi's code: a function (casadi_f3), a sparsity table (casadi_s2), ...
_NUMBERED = re.compile(r"casadi_[a-z]+\d+\b")         # (whole words: see _words)
_PREFIX_DEFINE = re.compile(r"^#define (casadi_\w+) CASADI_PREFIX\(\w+\)$")
#: Macros of CasADi's preamble a unit carries only if its code uses them.
_OPTIONAL_MACROS = ("casadi_to_int", "casadi_inf", "CASADI_CAST", "CASADI_SYMBOL_EXPORT")


class CasadiCode:
    """CasADi's generated code of a bundle, split into top-level blocks (static helpers, tables
    and functions), with the name and signature of each function block."""

    def __init__(self, source: str, prefix: str):
        self.prefix = prefix
        lines = source.splitlines()
        self.preamble: list[list[str]] = []               # chunks: one line, or one #if ... #endif group
        self.blocks: dict[str, str] = {}                   # symbol -> its definition, in CasADi's order
        self.names: dict[str, str] = {}                    # casadi_fN -> the CasADi function's name
        self.signatures: dict[str, str] = {}               # casadi_fN -> "name:(inputs)->(outputs)"
        starts = {a: (name, b) for name, a, b in _static_blocks(lines)}
        i = 0
        while i < len(lines):
            if i in starts or (i + 1 in starts and _SIGNATURE_COMMENT.match(lines[i])):
                first = i
                name, end = starts[i] if i in starts else starts[i + 1]
                if i not in starts:
                    self.names[name] = _SIGNATURE_COMMENT.match(lines[i]).group(1)
                    self.signatures[name] = lines[i][3:-3]
                self.blocks[name] = "\n".join(lines[first:end + 1])
                i = end + 1
            elif _PREFIX_DEFINE.match(lines[i]) or lines[i].startswith("/* Add prefix to internal symbols */"):
                i += 1
            elif lines[i].startswith("#if"):
                end = _end_of_conditional(lines, i)
                self.preamble.append(lines[i:end + 1])
                i = end + 1
            else:
                self.preamble.append([lines[i]])
                i += 1
        self.uses = {name: set(_words(_IDENT, text)) & set(self.blocks) - {name} for name, text in self.blocks.items()}
        self._hashes: dict[str, str] = {}
        #: the preamble's chunks (blank runs and the comment on dropped exports left out), each with
        #: the optional macros it defines
        self.chunks: list[tuple[str, set[str]]] = []
        for chunk in self.preamble:
            text = "\n".join(chunk)
            if text.startswith("/* Configuration this file was compiled with") or \
                    (text == "" and self.chunks and self.chunks[-1][0] == ""):
                continue
            self.chunks.append((text, {m for m in _OPTIONAL_MACROS if re.search(rf"#\s*define {m}\b", text)}))

    @classmethod
    def of(cls, bundle: Bundle) -> "CasadiCode":
        """One code generator over every kernel of the bundle, then the text passes below."""
        prefix = f"{bundle.model_name}_casadi"
        gen = ca.CodeGenerator(prefix, {"with_header": False, "include_math": False,
                                        "casadi_int": "int", "prefix": prefix})
        for kernel in bundle.kernels:
            gen.add(kernel.function)
        code = _void_unused_parameters(_inline_helpers(_single_copies(_internalise(gen.dump()))))
        return cls(_typed_literals(_math_macros(code)), prefix)

    def unit_symbols(self, model: str) -> dict[str, str]:
        """casadi_fN -> C symbol of every function that gets its own unit: the kernels and the
        functions named ``<model>_...`` whose code is the same wherever they occur."""
        by_name: dict[str, set[str]] = {}
        for number, name in self.names.items():
            by_name.setdefault(name, set()).add(self._canonical(number))
        return {number: function_symbol(model, name) for number, name in self.names.items()
                if name.startswith(f"{model}_") and len(by_name[name]) == 1}

    def _canonical(self, symbol: str) -> str:
        """A hash of a block's code with the blocks it uses replaced by their hashes (equal hashes:
        the same code, whatever CasADi numbered it)."""
        if symbol not in self._hashes:
            uses = self.uses[symbol]
            text = re.sub(r"^/\* \w+:", "/* :", self.blocks[symbol])
            text = _sub_words(_IDENT, lambda name: "casadi_self" if name == symbol else
                              self._canonical(name) if name in uses else name, text)
            self._hashes[symbol] = "casadi_h" + hashlib.sha256(text.encode()).hexdigest()[:16]
        return self._hashes[symbol]

    def unit(self, number: str, symbols: dict[str, str]) -> str:
        """The code of the unit defining function ``number`` as ``symbols[number]``
        (SYMKF_INTERNAL): the static blocks it uses, and prototypes of the unit functions it calls."""
        defined, declared, stack = set(), set(), [number]
        while stack:
            name = stack.pop()
            if name not in defined:
                defined.add(name)
                for used in self.uses[name]:
                    if used in symbols and used != number:
                        declared.add(used)
                    else:
                        stack.append(used)
        body = "\n\n".join(self.blocks[name] for name in self.blocks if name in defined)
        body = body.replace(f"static int {number}(", f"SYMKF_INTERNAL int {number}(", 1)
        local, counts = {}, Counter()
        for used in _words(_NUMBERED, body):
            if used in symbols:
                local[used] = symbols[used]
            elif used not in local and used in defined:
                kind = used.rstrip("0123456789")
                local[used], counts[kind] = f"{kind}{counts[kind]}", counts[kind] + 1
        body = _sub_words(_NUMBERED, lambda name: local.get(name, name), body)
        statics = sorted({local.get(name, name) for name in defined if name != number}, key=_natural)
        # its own symbol too: declared before it is defined (MISRA C:2012 rule 8.4)
        prototypes = sorted({symbols[name] for name in declared} | {symbols[number]})
        return "\n".join(self._preamble(symbols[number], body)
                         + ["/* Add prefix to internal symbols */"]
                         + [f"#define {name} CASADI_PREFIX({name[len('casadi_'):]})" for name in statics]
                         + [""] + [f"SYMKF_INTERNAL int {name}(const casadi_real** arg, casadi_real** res, "
                                   f"casadi_int* iw, casadi_real* w, int mem);   /* in {name}.c */"
                                   for name in prototypes]
                         + ["", body, ""])

    def _preamble(self, symbol: str, body: str) -> list[str]:
        """CasADi's preamble for one unit: its own symbol prefix; macros the body does not use left out."""
        used = {name for name in _OPTIONAL_MACROS if name in body and re.search(rf"\b{name}\b", body)}
        out = []
        for text, optional in self.chunks:
            if optional and not optional & used:
                if out and out[-1].startswith("/*"):             # its comment goes with it
                    out.pop()
            elif not (text == "" and out and out[-1] == ""):
                out.append(text.replace(f"{self.prefix}_ ##", f"{symbol}_casadi_ ##"))
        return out


def _natural(name: str) -> tuple:
    """Sort key: casadi_s2 before casadi_s10."""
    match = re.fullmatch(r"(\D+)(\d*)", name)
    return (match.group(1), int(match.group(2) or 0)) if match else (name, 0)


def _end_of_conditional(lines: list[str], start: int) -> int:
    """The line of the #endif closing the #if/#ifdef/#ifndef at ``start``."""
    depth = 0
    for j in range(start, len(lines)):
        stripped = lines[j].lstrip()
        if stripped.startswith("#if"):
            depth += 1
        elif stripped.startswith("#endif"):
            depth -= 1
            if depth == 0:
                return j
    raise ValueError(f"unterminated #if in CasADi's code at line {start + 1}")


_EXPORTED = re.compile(r"^CASADI_SYMBOL_EXPORT [\w ]+?\**\s*\**(\w+)\(")
_TOP_LEVEL_FUNCTION = re.compile(r"^(?:void|casadi_real|casadi_int|int|const [\w ]+?)\s*\**\s*\w+\((?!.*;\s*$)")


def _internalise(source: str) -> str:
    """Drop CasADi's exported functions (the entry wrappers and reflection: n_in, sparsity_in,
    incref, ...); make every helper static."""
    out, lines, i = [], source.splitlines(), 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("CASADI_SYMBOL_EXPORT") and _EXPORTED.match(line):
            i = (i if line.rstrip().endswith("}") else _closing_brace(lines, i)) + 1
            continue
        out.append("static " + line if line[:1].isalpha() and _TOP_LEVEL_FUNCTION.match(line) else line)
        i += 1
    return "\n".join(out) + "\n"


#: The comment CasADi writes above each function it generates: ``/* name:(inputs)->(outputs) */``.
_SIGNATURE_COMMENT = re.compile(r"^/\* (\w+):\(")

_COPY_LOOP = re.compile(r"for \(rr=\(&(w\d+)\), cs=(\w+)(?:\+(\d+))?; cs!=\2\+(\d+); cs\+=1\) \*rr\+\+ = \*cs;")


def _single_copies(source: str) -> str:
    """CasADi copies one element into a scalar with a pointer loop, ``for (rr=(&w27), cs=w09+1;
    cs!=w09+2; cs+=1) *rr++ = *cs;``, which GCC at -O1 cannot prove runs once: it then reports
    the scalar as maybe uninitialized (an error under -Werror). Written as the one copy it is,
    ``rr=(&w27); cs=w09+1; *rr = *cs;``, the same assignment, proved at every -O level."""
    def one(match: re.Match) -> str:
        first, end = int(match.group(3) or 0), int(match.group(4))
        if end != first + 1:
            return match.group(0)
        offset = f"+{first}" if match.group(3) else ""
        return f"rr=(&{match.group(1)}); cs={match.group(2)}{offset}; *rr = *cs;"
    return _COPY_LOOP.sub(one, source)


_HELPER = re.compile(r"^static (void|casadi_real) (casadi_(?:sq|copy|fmax|fmin|fabs))\(", re.M)


def _inline_helpers(source: str) -> str:
    """CasADi's small static helpers (``casadi_sq``, ``casadi_copy``, ``casadi_fmax``, ...)
    declared ``static inline`` (C99), so that GCC at -O1 inlines them instead of calling them:
    the same statements (x*x is x*x), without a call per use (before: 138 calls of ``casadi_sq``
    per UKF prediction, 268 instructions per step; bit-identical results)."""
    return _HELPER.sub(r"static inline \1 \2(", source)


_IDENT = re.compile(r"casadi_\w+")                     # (whole words: see _words)


def _whole(match: re.Match) -> bool:
    """The match is not the tail of a longer word (what a leading \\b would test: patterns that
    start with a literal instead let the scanner jump to it, 40 times faster on CasADi's code)."""
    start = match.start()
    return start == 0 or not (match.string[start - 1].isalnum() or match.string[start - 1] == "_")


def _words(pattern: re.Pattern, text: str) -> list[str]:
    """The whole-word matches of ``pattern`` in ``text`` (as findall with a leading \\b)."""
    return [m.group(0) for m in pattern.finditer(text) if _whole(m)]


def _sub_words(pattern: re.Pattern, replace, text: str) -> str:
    """``text`` with each whole-word match of ``pattern`` replaced by ``replace(match text)``."""
    return pattern.sub(lambda m: replace(m.group(0)) if _whole(m) else m.group(0), text)


_STATIC_DEFINITION = re.compile(r"^static [^=(]*?\b(casadi_\w+)\s*[\[(]")


def _static_blocks(lines: list[str]) -> list[tuple[str, int, int]]:
    """(name, first line, last line) of every top-level static function or table."""
    blocks, i = [], 0
    while i < len(lines):
        match = _STATIC_DEFINITION.match(lines[i]) if lines[i].startswith("static ") else None
        if not match:
            i += 1
            continue
        end = i
        if match.group(0).endswith("["):                              # a table: up to its ';'
            while not lines[end].rstrip().endswith(";"):
                end += 1
        elif not (lines[i].rstrip().endswith("}") and "{" in lines[i]):  # a function over several lines
            end = _closing_brace(lines, i)
        blocks.append((match.group(1), i, end))
        i = end + 1
    return blocks


def _closing_brace(lines: list[str], start: int) -> int:
    for j in range(start + 1, len(lines)):
        if lines[j].rstrip() == "}":
            return j
    raise ValueError(f"unterminated function in CasADi's code at line {start + 1}")


def _math_macros(source: str) -> str:
    """sin( -> SYMKF_SIN( etc., so a float build calls sinf explicitly (MISRA C:2012 rule 21.11)."""
    def macro(match: re.Match) -> str:
        before = match.string[match.start() - 1] if match.start() else " "
        name = match.group(0)[:-1]
        return _MATH_MACRO[name] if name in _MATH_MACRO and not (before.isalnum() or before == "_") else match.group(0)
    return _LOWER_CALL.sub(macro, source)


#: A floating literal: digits (the first not after a letter, digit, _ or .), then a fraction
#: and/or an exponent (the look-behind after the first digit lets the scan skip to digits).
_FLOAT_LITERAL = re.compile(r"(\d(?<![\w.]\d)\d*(?:\.\d*(?:[eE][+-]?\d+)?|[eE][+-]?\d+))")


def _typed_literals(source: str) -> str:
    """Cast floating literals to casadi_real, so a float build does no double arithmetic."""
    return _FLOAT_LITERAL.sub(r"((casadi_real)\1)", source)


_DEFINITION = re.compile(r"^(?:static |CASADI_SYMBOL_EXPORT )?[\w ]+?\b(\w+)\(([^()]*)\)\s*\{\s*$")


def _void_unused_parameters(source: str) -> str:
    """Insert ``(void)param;`` at the top of every function definition (-Wunused-parameter)."""
    out = []
    for line in source.splitlines():
        out.append(line)
        match = _DEFINITION.match(line) if line[:1].isalpha() else None
        if match and match.group(2).strip() not in ("", "void"):
            names = [p.strip().split()[-1].lstrip("*") for p in match.group(2).split(",")]
            out.append("  " + " ".join(f"(void){name};" for name in names))
    return "\n".join(out) + "\n"


def math_block(code: str | None = None) -> str:
    """The SYMKF_<NAME> macros: double functions, or float ones under -DSYMKF_FLOAT; with
    ``code``, only those it calls (no unused macro: MISRA C:2012 rule 2.5)."""
    names = [n for n in MATH_FUNCTIONS if code is None or f"SYMKF_{n.upper()}(" in code]
    if not names:
        return "/* (no math function called) */"
    lines = ["#ifdef SYMKF_FLOAT"]
    lines += [f"#define SYMKF_{name.upper()} {name}f" for name in names]
    lines += ["#else"]
    lines += [f"#define SYMKF_{name.upper()} {name}" for name in names]
    lines += ["#endif"]
    return "\n".join(lines)
