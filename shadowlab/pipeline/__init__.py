"""The main jobs, as functions the CLI and tests call: make a reference, compare techniques.

    reference(scene)  : scene -> FrameContext -> ground truth -> references/<scene>/<W>x<H>/
    compare(scene, …) : scene -> FrameContext (once) -> each technique -> metrics -> report

A scene with a camera path has one truth per frame (``frame=`` / ``frames=``; the store keeps them
in ``<W>x<H>-f<NNNN>/``). ``compare(..., frames=(A, B))`` writes one report per frame and a
top-level page with a technique × frame table and the temporal stability (shimmer,
:mod:`shadowlab.metrics.temporal`) of every technique, measured at the first frame's G-buffer
points while each frame's light views follow that frame's camera (:func:`shimmer`).

Modules: ``args`` (the shared options, parsed and checked), ``references`` (truth jobs on any
executor), ``compare`` (techniques against the truth, the typed run, reports), ``shimmer``.
"""

from .args import check_memory, check_reference_args, frame_list, parse_frames, parse_resolution
from .compare import compare, error_bands, run_techniques, technique_metrics
from .references import (ReferenceJob, load_scene, reference, reference_batch, reference_frames, reference_jobs,
                         render_reference_job)
from .shimmer import shimmer

__all__ = ["parse_resolution", "check_reference_args", "check_memory", "parse_frames", "frame_list", "load_scene",
           "reference",
           "reference_frames", "ReferenceJob", "reference_jobs", "render_reference_job", "reference_batch",
           "run_techniques", "technique_metrics", "error_bands", "shimmer", "compare"]
