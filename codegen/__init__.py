"""Model -> CasADi Functions -> C: discretisation, derived Jacobians, fused filter kernels, build.

Three verbs, each callable on its own: :func:`generate` (kernels), :func:`build_model`
(write + compile, content-hash cached), and ``symkf.runtime.load`` (bind the library).
"""
from .build import (BuildError, BuildResult, CompilerNotFound, build_model, build_root, compiler,
                    content_hash, generate, make_config)
from .spec import STATUS_CODES, Arg, Bundle, CodegenConfig, Kernel

__all__ = ["Arg", "Bundle", "BuildError", "BuildResult", "CodegenConfig", "CompilerNotFound", "Kernel",
           "STATUS_CODES", "build_model", "build_root", "compiler", "content_hash", "generate", "make_config"]
