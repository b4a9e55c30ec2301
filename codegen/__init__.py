"""Model -> CasADi Functions -> C: discretisation, derived Jacobians, fused filter kernels, build.

Three verbs, each callable on its own: :func:`generate` (kernels), :func:`build_model`
(write + compile, cached by a hash of what is generated), and ``symkf.runtime.load`` (bind the
library). A model is anything :func:`symkf.models.get_model` accepts (a paper model's short name,
a file path, a module name, a module or a Model).
"""
from .build_folders import build_root
from .compilation import compiler
from .errors import BuildError, BundleRepairWarning, CompilerNotFound
from .generation import config_for, generate, generate_validated, make_config
from .hashing import content_hash, generated_hash
from .lifecycle import BuildResult, build_model, build_validated, export_bundle
from .spec import STATUS_CODES, Arg, Bundle, CodegenConfig, Family, FilterSpec, Kernel

__all__ = ["Arg", "Bundle", "BuildError", "BuildResult", "BundleRepairWarning", "CodegenConfig", "CompilerNotFound", "Family", "FilterSpec",
           "Kernel", "STATUS_CODES", "build_model", "build_root", "build_validated", "compiler", "config_for",
           "content_hash", "export_bundle", "generate", "generate_validated", "generated_hash", "make_config"]
