"""Reconstruction algorithms, arrays in, arrays out: one module per family, a method registry each.

:mod:`.hdr` merges of exposure series (``HDR_METHODS``); :mod:`.phase` structured light's phase
shifting, Gray codes and unwrapping (``UNWRAP_METHODS``); :mod:`.deblur` coded-exposure blur kernels
and deconvolution; :mod:`.register` frame registration and burst averaging (``ALIGN_METHODS``);
:mod:`.matting` trimaps and alpha matting (``MATTING_METHODS``). The applications
(:mod:`mbcapture.apps`) capture, render the truth and score; the figures call these directly.
"""

from .hdr import HDR_METHODS, HDRResult, merge_hdr

__all__ = ["HDR_METHODS", "HDRResult", "merge_hdr"]
