"""yauyau solver: the mathematics (pure numpy/scipy/SymPy; imports neither storage nor service)."""

from .errors import InputError, SpecError, YauyauError
from .model import Model, compile_model
from .spec import ModelSpec, load_spec, parse_spec_text, spec_from_dict

__all__ = [
    "InputError", "Model", "ModelSpec", "SpecError", "YauyauError",
    "compile_model", "load_spec", "parse_spec_text", "spec_from_dict",
]
