"""The tensor engine: a photo's segments in, a camera and how far to trust it out.

Rooms, lowest first; a module imports only its own room and the rooms below it
(:data:`ROOMS`; ``tests/test_layers.py`` checks it):

0. :mod:`~fr_torch.core.exact` and :mod:`~fr_torch.core.exact_math` -- arithmetic that gives the
   same bits in any batch, thread count, kernel set and CPU: exact sums, written-out products,
   small linear solves, tie rules, and ``exp`` / ``log`` / ``atan`` / ... spelled out.
1. :mod:`~fr_torch.core.geometry` -- the camera model: conventions, the ``Camera`` value type, the
   horizon, parameter rows, the division lens, vanishing points and Atlanta families.
2. :mod:`~fr_torch.core.settings` -- a user's settings parsed once into types: input checks, FOV
   range, lens setting, ``Mode``, ``SearchConfig``.
3. :mod:`~fr_torch.core.likelihood` -- segments as the engine sees them, the deviation measures,
   the mixture, the fused objective and its C kernels.
4. :mod:`~fr_torch.core.search` -- one engine (grid -> passes -> refine) and the fits that use it
   (Manhattan, with extra horizontal families, and lens).
5. :mod:`~fr_torch.core.reliability` -- cues, the error model, the promise's bounds, sanity checks.
6. :mod:`~fr_torch.core.estimator` (:class:`~fr_torch.core.estimator.SegmentEstimator`: padded
   segment batches through the rooms), :mod:`~fr_torch.core.result`
   (:class:`~fr_torch.core.result.CalibrationResult`) and :mod:`~fr_torch.core.exports` (camera
   files for COLMAP and OpenCV).

No file I/O beyond the shipped configuration files, no argparse, no processes: everything here runs
on tensors (CPU or CUDA) and is what the layers above (:mod:`fr_torch.runtime`, :mod:`fr_torch.cli`)
call.  ``docs/architecture.md`` draws the rooms and the path a photo's segments take through them.
"""

#: The rooms, lowest first, each the names of its first level below ``fr_torch.core`` (a subpackage,
#: or the top-level modules that form the room); its first name labels it.
ROOMS = (("exact", "exact_math"), ("geometry",), ("settings",), ("likelihood",), ("search",), ("reliability",),
         ("estimator", "result", "exports"))
