"""Typed descriptions of what codegen produces: kernels, their arguments, build settings.

A *kernel* is one CasADi Function that becomes one C entry point. Its last output is always a
scalar ``status`` (0 = success, otherwise one of :data:`STATUS_CODES`); the C wrapper turns it
into the return code and leaves every output untouched on failure.

Build settings: :class:`CodegenConfig`, whose ``extra`` options are declared by their readers as
frozen dataclasses (:func:`declare_options`, a family's through ``register_family``), each field
one option with its type, default and meaning; :func:`codegen_options` lists them all.
"""
from __future__ import annotations

import typing
from dataclasses import dataclass, field, fields, replace

import casadi as ca

#: Return codes shared by the generated C and the Python runtime.
STATUS_CODES = {
    0: ("SYMKF_OK", "success"),
    1: ("SYMKF_ERR_EVAL", "the generated function reported an evaluation error"),
    2: ("SYMKF_ERR_NOT_PD", "a covariance (P, or the innovation covariance S) is not positive definite"),
    3: ("SYMKF_ERR_NONFINITE", "an input or result is NaN or infinite"),
    4: ("SYMKF_ERR_DOMAIN", "an argument is outside the domain of the equations (e.g. |dp| >= 1 or n + kappa <= 0)"),
    5: ("SYMKF_ERR_ARGS", "a bad argument (e.g. a negative step count, or an R with correlations for an update "
        "that is sequential: manifold_update=\"sequential\" needs a diagonal R)"),
    6: ("SYMKF_GATED", "the innovation failed the chi-square gate (y^T S^-1 y > gate); the update was skipped"),
}
STATUS_OK, STATUS_EVAL, STATUS_NOT_PD, STATUS_NONFINITE, STATUS_DOMAIN, STATUS_ARGS, STATUS_GATED = range(7)


@dataclass(frozen=True)
class Arg:
    """One argument of a kernel: its name, dense shape, unit and meaning."""

    name: str
    shape: tuple[int, int]
    unit: str = "-"
    description: str = ""

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    def as_dict(self) -> dict:
        return {"name": self.name, "shape": list(self.shape), "unit": self.unit,
                "description": self.description}


@dataclass(frozen=True)
class Kernel:
    """A CasADi Function destined to become the C function ``<model>_<name>``.

    Attributes:
        name: C-safe name, unique within the model.
        function: the CasADi Function; inputs/outputs in the order of ``inputs``/``outputs``.
        doc: one paragraph for the header and manifest.
        inputs, outputs: argument descriptions (outputs end with ``status``).
        carried: names of outputs that feed back into the same-named inputs in a run loop
            (e.g. ``("x", "P")``); empty for kernels that are not filter steps.
        per_step: names of inputs that change every step of a run (e.g. ``t``, ``z``).
        parts: for a fused step (``compose_step``), the names of its predict and update kernels:
            the C API calls those two (the step's own Function is their composition, for the VM).
        trusted: for a runnable kernel, the name of a kernel with the same arguments that the C run
            loop iterates instead once the carried state is the loop's own (a step succeeded): it
            leaves out the checks of x and P (and of fixed inputs) that such a state and the inputs
            a successful step already passed cannot fail (e.g. |q| = 1, R diagonal), or "" (none).
        variants: specialisations of this kernel that its C wrapper and a run loop call instead
            when some input entries are exactly 0: ``((kernel name, ((input name, (entry, ...)),
            ...)), ...)``, entries in column-major order; the first whose entries are all 0 is
            called (in a run: a fixed input's once per run, a per-step input's at each step). Each
            is this kernel with those entries replaced by the constant 0, which CasADi folds away
            (e.g. a masked component's scalar update, a gate that is off): the same outputs.
        backward: for a smoother's backward step (codegen/families/rts.py), the outputs that feed
            back into the same-named inputs of the step before it (``("xs", "Ps")``): the C backend
            generates a backward ``_run`` loop over a forward run's histories for it.
    """

    name: str
    function: ca.Function
    doc: str
    inputs: tuple[Arg, ...]
    outputs: tuple[Arg, ...]
    carried: tuple[str, ...] = ()
    per_step: tuple[str, ...] = ()
    parts: tuple[str, ...] = ()
    trusted: str = ""
    variants: tuple = ()
    backward: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        f = self.function
        if f.n_in() != len(self.inputs) or f.n_out() != len(self.outputs):
            raise ValueError(f"kernel '{self.name}': {f.n_in()} inputs/{f.n_out()} outputs in the Function, "
                             f"{len(self.inputs)}/{len(self.outputs)} described")
        for i, arg in enumerate(self.inputs):
            if tuple(f.size_in(i)) != arg.shape:
                raise ValueError(f"kernel '{self.name}': input '{arg.name}' is {f.size_in(i)}, described {arg.shape}")
        for i, arg in enumerate(self.outputs):
            if tuple(f.size_out(i)) != arg.shape:
                raise ValueError(f"kernel '{self.name}': output '{arg.name}' is {f.size_out(i)}, described {arg.shape}")
        if self.outputs[-1].name != "status" or self.outputs[-1].shape != (1, 1):
            raise ValueError(f"kernel '{self.name}': the last output must be the scalar 'status'")

    @property
    def runnable(self) -> bool:
        """True if a C run loop is generated for it (it carries a filter state)."""
        return bool(self.carried)

    def input_index(self, name: str) -> int:
        return [a.name for a in self.inputs].index(name)

    def ignores(self) -> list[str]:
        """Of the inputs a caller might forget (``u``), those no output but ``status`` depends on
        (an update whose h does not read the input): the runtime does not ask for them."""
        outputs = [a.name for a in self.outputs[:-1]]
        names = [a.name for a in self.inputs]
        return [name for name in ("u",) if name in names and outputs
                and not any(self.function.which_depends(name, outputs, 1, True))]

    def as_dict(self) -> dict:
        f = self.function
        return {"name": self.name, "doc": self.doc,
                "inputs": [a.as_dict() for a in self.inputs],
                "outputs": [a.as_dict() for a in self.outputs],
                "carried": list(self.carried), "per_step": list(self.per_step), "trusted": self.trusted,
                "ignores": self.ignores(),
                "backward": list(self.backward),
                "work": {"arg": f.sz_arg(), "res": f.sz_res(), "iw": f.sz_iw(), "w": f.sz_w()},
                "instructions": f.n_instructions()}


class ConfigError(ValueError):
    """A codegen option that is unknown or has a value its reader does not accept."""


@dataclass(frozen=True)
class Option:
    """One codegen option beyond CodegenConfig's fields, as its readers declare it.

    Attributes:
        name: the key of ``CodegenConfig.with_overrides`` and ``CodegenConfig.get``.
        type: the accepted type (a class or a union; ``object``: any value).
        default: the value used when the option is not set (None: derived, see ``meaning``).
        meaning: one line for the documentation and the ``symkf options`` listing.
        readers: who reads it (a family, a codegen module).
    """

    name: str
    type: object
    default: object
    meaning: str
    readers: tuple[str, ...] = ()

    def accepts(self, value) -> bool:
        """True if ``value`` has the declared type (a bool is not an int)."""
        if self.type is object:
            return True
        if isinstance(value, bool) and not _admits_bool(self.type):
            return False
        return isinstance(value, self.type)

    @property
    def type_name(self) -> str:
        return getattr(self.type, "__name__", None) or str(self.type)


def _admits_bool(kind) -> bool:
    return kind is bool or bool in getattr(kind, "__args__", ())


#: Codegen options beyond CodegenConfig's fields, by name: each module that reads one declares it
#: with :func:`declare_options` (a frozen dataclass whose fields are the options).
OPTIONS: dict[str, Option] = {}


def option(default, meaning: str):
    """A field of an options dataclass: its default and its one-line meaning (the type is the
    field's annotation)."""
    return field(default=default, metadata={"meaning": meaning})


def declare_options(options: type, reader: str, prefix: str = "") -> None:
    """Declare every field of the frozen dataclass ``options`` as the codegen option
    ``<prefix><field>``, read by ``reader``. The same option declared again (another family
    reading it) adds its reader; a different type or default is an error."""
    hints = typing.get_type_hints(options)
    for f in fields(options):
        made = Option(prefix + f.name, hints[f.name], f.default, f.metadata.get("meaning", ""), (reader,))
        known = OPTIONS.get(made.name)
        if known is None:
            OPTIONS[made.name] = made
        elif (known.type, known.default) != (made.type, made.default):
            raise ValueError(f"codegen option '{made.name}' declared twice with different types or defaults")
        elif reader not in known.readers:
            OPTIONS[made.name] = replace(known, readers=known.readers + (reader,))


@dataclass(frozen=True)
class NumericOptions:
    """The number format of a build (read by :class:`CodegenConfig`)."""

    precision: str = option("double", "casadi_real of the build: 'double' or 'float' (the C type of every number)")
    scaling: bool = option(None, "filters work on the scaled state x~ = (x - offset) / scale, with the scale "
                                 "and offset of each Model.state(); default: on for float, off for double")


declare_options(NumericOptions, "CodegenConfig")


def codegen_options() -> list[Option]:
    """Every codegen option: CodegenConfig's fields, then the declared options by name (those of
    every family once ``symkf.codegen`` is imported, which imports them all)."""
    hints = typing.get_type_hints(CodegenConfig)
    own = [Option(f.name, hints[f.name], f.default, f.metadata.get("meaning", ""), ("codegen",))
           for f in fields(CodegenConfig) if f.name != "extra"]
    return own + [OPTIONS[name] for name in sorted(OPTIONS)]


@dataclass(frozen=True)
class CodegenConfig:
    """Settings that change the generated code (all part of the build's content hash).

    Attributes:
        rk4_substeps: RK4 sub-steps per filter step in the discretised dynamics.
        optimization: the C compiler's -O level for the Python-loaded library.
        extra: per-family settings (e.g. a quaternion filter's iteration count).
    """

    rk4_substeps: int = option(1, "RK4 sub-steps per filter step in the discretised dynamics")
    optimization: str = option("-O3 -fno-math-errno", "the C compiler's -O level and flags for the library")
    extra: tuple[tuple[str, object], ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.rk4_substeps, bool) or not isinstance(self.rk4_substeps, int) or self.rk4_substeps < 1:
            raise ConfigError(f"rk4_substeps: expected an integer >= 1, got {self.rk4_substeps!r}")
        if not isinstance(self.optimization, str) or not self.optimization.startswith("-O"):
            raise ConfigError(f"optimization: expected compiler flags starting with -O, got {self.optimization!r}")

    def with_overrides(self, **changes) -> "CodegenConfig":
        """A new config with the given fields changed; this one is left as it is. An option that
        no part of codegen declares (:data:`OPTIONS`), or a value not of its declared type, is a
        :class:`ConfigError` (a misspelt option must not build)."""
        unknown = sorted(k for k in changes if k not in self.__dataclass_fields__ and k not in OPTIONS)
        if unknown:
            known = sorted(set(self.__dataclass_fields__) - {"extra"} | set(OPTIONS))
            raise ConfigError(f"unknown codegen option(s) {unknown}; known: {', '.join(known)}")
        for key, value in changes.items():
            if key in OPTIONS and not OPTIONS[key].accepts(value):
                raise ConfigError(f"{key}: expected a value of type {OPTIONS[key].type_name}, got {value!r}")
        known = {k: v for k, v in changes.items() if k in self.__dataclass_fields__}
        extra = dict(self.extra)
        extra.update({k: v for k, v in changes.items() if k not in self.__dataclass_fields__})
        return replace(self, **known, extra=tuple(sorted(extra.items())))

    def get(self, key: str, default=None):
        return dict(self.extra).get(key, default)

    @property
    def precision(self) -> str:
        """"double" (default) or "float": the build's casadi_real (``precision="float"``)."""
        value = self.get("precision", "double")
        if value not in PRECISIONS:
            raise ConfigError(f"precision: expected one of {list(PRECISIONS)}, got {value!r}")
        return value

    @property
    def scaled(self) -> bool:
        """True if the filters work on the model's scaled state x~ = (x - offset) / scale
        (codegen/scaling.py). Option ``scaling``: default on for float, off for double."""
        value = self.get("scaling", self.precision == "float")
        if not isinstance(value, bool):
            raise ConfigError(f"scaling: expected True or False, got {value!r}")
        return value


#: The floating-point types a build can use for casadi_real.
PRECISIONS = ("double", "float")


@dataclass(frozen=True)
class FilterSpec:
    """Which kernels make up one filter, so the runtime can build it without knowing the family.

    Attributes:
        name: the filter's name within the model ("ekf", "ukf", "cd_ekf", "mekf", "gd_simple_marg"...).
        algorithm: the algorithm, which names its NumPy reference ("ekf", "ukf", "cd_ekf", "mekf",
            "qukf", "aukf", "gd_simple", "gd_full").
        predict: the prediction kernel ("" if the filter has none: it only steps).
        update, step: {measurement: kernel}; ``step`` = predict then update in one call; a step
            kernel is also the one the C run loop iterates (``Kernel.carried``), unless ``run`` names
            another.
        run: {measurement: kernel} the run loop iterates instead of the step kernel: the same step
            without the diagnostics (y, S), which a run discards (default: the step kernel).
        state: outputs carried from step to step (``("x", "P")`` or ``("x",)``).
        diagnostics: per-measurement outputs a user inspects after an update (``("y", "S")``).
        measurement_inputs: per-measurement inputs (``q``, ``z``, ``mask``, ``R``, ``gate``, or a
            MARG filter's ``acc``, ``mag``); every other input is shared by all kernels.
        defaults: default values of scalar inputs (e.g. ``{"kappa": 0.0}``).
        covariance: what the carried ``P`` holds: "full" (the covariance) or "cholesky" (its lower
            Cholesky factor L, P = L L^T: the square-root families; the runtime converts).
        smooth: the kernel of the fixed-interval (RTS) smoother's backward step ("" if the
            filter has none): its ``_run`` loop smooths a forward run's histories.
    """

    name: str
    algorithm: str
    predict: str
    update: dict[str, str]
    step: dict[str, str]
    state: tuple[str, ...] = ("x", "P")
    diagnostics: tuple[str, ...] = ("y", "S")
    measurement_inputs: tuple[str, ...] = ("q", "z", "mask", "R", "gate")
    defaults: dict[str, float] = field(default_factory=dict)
    run: dict[str, str] = field(default_factory=dict)
    covariance: str = "full"
    smooth: str = ""

    @property
    def measurements(self) -> tuple[str, ...]:
        return tuple(self.step)

    def kernel_names(self) -> list[str]:
        return ([self.predict] if self.predict else []) + list(self.update.values()) + list(self.step.values())

    def as_dict(self) -> dict:
        return {"name": self.name, "algorithm": self.algorithm, "predict": self.predict,
                "update": dict(self.update), "step": dict(self.step), "state": list(self.state),
                "diagnostics": list(self.diagnostics), "measurement_inputs": list(self.measurement_inputs),
                "defaults": dict(self.defaults), "run": dict(self.run),
                "covariance": self.covariance, "smooth": self.smooth}

    @classmethod
    def from_dict(cls, entry: dict) -> "FilterSpec":
        return cls(entry["name"], entry["algorithm"], entry["predict"], dict(entry["update"]),
                   dict(entry["step"]), tuple(entry["state"]), tuple(entry["diagnostics"]),
                   tuple(entry["measurement_inputs"]), dict(entry["defaults"]), dict(entry.get("run", {})),
                   entry.get("covariance", "full"), entry.get("smooth", ""))


@dataclass
class Family:
    """What a filter family generates for a model: its kernels and the filters they make up."""

    kernels: list[Kernel]
    filters: list[FilterSpec] = field(default_factory=list)


@dataclass
class Bundle:
    """Everything generated for one model: the kernels, the filters they make up, and a description."""

    model_name: str
    kernels: list[Kernel]
    config: CodegenConfig
    description: dict = field(default_factory=dict)
    filters: list[FilterSpec] = field(default_factory=list)
    #: How many kernels each generation step made, in order (the model's own kernels, then each
    #: filter family's); () = one part. The C of each part is generated on its own (c_backend.units).
    parts: tuple[int, ...] = ()
    #: The scalar units the host library evaluates in SIMD lanes (c_backend/lanes.py LaneSpec).
    lanes: tuple = ()
    #: The fused steps the host library also steps in lockstep, several runs per vector
    #: (c_backend/lockstep.py LockstepSpec).
    lockstep: tuple = ()

    def part_bundles(self) -> list["Bundle"]:
        """The bundle of each part's kernels (the whole bundle if it has no parts)."""
        if not self.parts:
            return [self]
        if sum(self.parts) != len(self.kernels):
            raise ValueError(f"model '{self.model_name}': parts {self.parts} do not add up to {len(self.kernels)} kernels")
        starts = [sum(self.parts[:i]) for i in range(len(self.parts))]
        return [Bundle(self.model_name, self.kernels[a:a + n], self.config, self.description, lanes=self.lanes)
                for a, n in zip(starts, self.parts)]

    def filter(self, name: str) -> FilterSpec:
        for spec in self.filters:
            if spec.name == name:
                return spec
        raise KeyError(f"model '{self.model_name}' has no filter '{name}'; it has {[f.name for f in self.filters]}")

    def kernel(self, name: str) -> Kernel:
        for k in self.kernels:
            if k.name == name:
                return k
        raise KeyError(f"model '{self.model_name}' has no kernel '{name}'; "
                       f"it has {[k.name for k in self.kernels]}")
