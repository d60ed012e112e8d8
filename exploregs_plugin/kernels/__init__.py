"""Compiled CPU kernels (C++ with OpenMP, built on first use): see ``build.py``."""

from .build import cpp_problem, extension

__all__ = ["cpp_problem", "extension"]
