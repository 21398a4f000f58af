"""The Mitsuba variant, chosen in one place: ``scene_gen.variant`` (a leaf module that both ``scene_gen``
and ``pipeline`` import; see its docstring). This module is its public name for the pipeline."""
from scene_gen.variant import choose_variant, cuda_available, find_libllvm, mitsuba  # noqa: F401
from scene_gen.errors import VariantError  # noqa: F401
