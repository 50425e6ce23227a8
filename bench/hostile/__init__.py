"""A hostile-input set of its own (not the rows of tests/commands/test_malformed.py), run the way a new user
would hit it, for BENCHMARKS' "Hostile inputs" section (issue 28, inputs part).

    python -m bench hostile                  # every case, ~5 min at 1 thread
    python -m bench hostile --limit 40       # a quick look

Classes of cases (each built here, in a temporary folder):

* ``numbers``: every numeric option of every command (``omnirecon.options.numeric_fields``) with values a
  user mistypes: ``nan``, ``inf``, ``-inf``, below and above its range, and a huge size.
* ``photos``: scenes of three formats and photo folders for ``process`` whose images are decompression
  bombs, truncated, empty, FIFOs, devices, folders or links to them; plus unusual *valid* photos (16-bit,
  palette, CMYK, grey + alpha), which must be *accepted* (exit 0, no traceback).
* ``files``: pose files with bad focal fields, deep JSON, NumPy headers claiming more than the file
  holds, unreadable mesh files as ``--mesh`` and as a scene's ground truth, broken checkpoint metadata.
* ``outputs``: ``--out`` under /proc, under a file, through a dangling link, on a device.
* ``outputs_user``: ``--out`` over a file (or into a folder) the user wrote: a mesh set's files, a bench
  JSON, a train folder's config, a file added to an earlier render output; refused, nothing replaced or lost.
* ``capture``: photos too small for SfM, a clip sampled above its own frame rate or at almost none.
* ``memory``: ``mesh --voxel`` and ``finetune --val-every`` values whose allocation exceeds the memory.
* ``viewer``: HTTP requests with several ``Host`` headers (must be 400), clients that disconnect, and up to
  1,000 connections that stall in their headers while a normal request must be answered within 1 s; bad requests
  (huge or endless headers, garbage, HTTP/0.9, traversal in every spelling, CONNECT, a body never sent), a
  slowloris trickle, clients that request a large file and never read it, connections that send nothing.

The set written for the verbs and options added since (:func:`fresh_cases`):

* ``video``: clips in 10-bit H.264 and HEVC, VP9, 16-bit FFV1, MPEG-4 and with a rotation must decode upright;
  corrupt, empty, truncated, audio-only, one- and two-frame, 2x2-pixel, FIFO, device and looping "videos" refused.
* ``folders_valid`` / ``folders``: photo folders of mixed sizes, CMYK / grey JPEG, 16-bit PNG, EXIF-rotated,
  WebP, BMP, TIFF (staged); and with a truncated JPEG / PNG, a JPEG claiming 65000 px sides, a link loop, a file
  reading fails on, HEIC, an animated GIF, a folder linking to itself, none / one / two photos (refused).
* ``options``: depth sources, surfaces (``--surface auto|fusion|coherent|poisson``), view lists, finetune blends
  and fills on a broken mesh, ``--guided.*`` on render / eval, ``process --learned`` and ``--masks`` (all black),
  ``bench --realtime --face-budget`` with a bad mesh; refused naming the option or file, or accepted.
* ``resume``: `reconstruct --resume / --no-resume` over an ``OUT.partial`` that is the user's folder, a file, a link
  (or holds a link as its record folder), or a garbage record: refused or started over, no file of the user's lost.

A refused case counts as handled only with exit 2, one stderr line ``omnirecon: error: ...`` naming the
file or option and carrying a ``(fix: ...)`` clause, no traceback, nothing added, removed or changed
under the fixtures, no ``--out`` and nothing in the working folder. Each case runs in a forked child (the
package imported once in the parent) with a time limit (a hang) and an address-space limit (killed for
memory). Writes ``bench/results/hostile.json`` with a provenance header.

The set is a package of one module per class (``numbers``, ``photos``, ``files``, ``outputs``, ``viewer``, ``video``,
``folders``, ``options``, ``resume``), the shared fixtures and the runner (``python -m bench hostile``:
:func:`bench.hostile.runner.main`).
"""

from bench.hostile.runner import EXTRA_MEMORY, TIMEOUT, cases, main, run_case
from bench.hostile.viewer import BAD_REQUESTS, http_exchange, stalled_then_get

__all__ = ["BAD_REQUESTS", "EXTRA_MEMORY", "TIMEOUT", "cases", "http_exchange", "main", "run_case", "stalled_then_get"]
