"""The build's errors: what failed, in one line that says how to fix it."""


class BuildError(RuntimeError):
    """Generating or compiling a model failed; the message says what and how to fix it."""


class CompilerNotFound(BuildError):
    """No C compiler: the runtime can still evaluate the kernels in CasADi's virtual machine."""


class BundleRepairWarning(UserWarning):
    """A build folder of the same sources had a file missing, damaged or edited: it is regenerated."""
