"""Reconstruction from sensor reads: one module per family, a method registry each."""

from .hdr import HDR_METHODS, HDRResult, merge_hdr

__all__ = ["HDR_METHODS", "HDRResult", "merge_hdr"]
