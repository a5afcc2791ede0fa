"""Memory estimate of a bake, checked once by ``checks.check_bake`` against ``memory_budget_gb``.

The bake holds, for every baked object until it returns (``results.ObjectBake``): its texels
(:data:`~lmdp_addon.bake.texels.TEXEL_BYTES` each), their value and standard error (2 x 3
float32), their batch means up to :data:`BATCH_MEANS_BYTES` and its R x R RGBA float32 image;
the Blender layer then writes each image into a Blender image of the same size. While one
object is baked it needs, on top, the largest of:

* rasterising it (``texels.RASTER_BYTES_PER_TEXEL`` per texel and a chunk of candidates);
* tracing it: the running sums of the batch means and their squares (2 x 3 float64), the nearest
  state of each texel (int64), and the work units in flight (``driver.PATHS_PER_UNIT`` paths
  each, :data:`PATH_BYTES` per path, and with path reuse a block of tile pairs each,
  :data:`REUSE_BLOCK_BYTES`);
* its statistics (the sums and one temporary, 3 x 3 float64) or its image (the texels' values as
  an image and the float64 copy and masks of the margin's dilation, :data:`FINISH_BYTES_PER_PIXEL`).

Plus the BVH and per-triangle tables of the tracer (:data:`TRIANGLE_BYTES`). The coefficients
are rounded up from the peak memory of bakes measured with ``tracemalloc`` and the process's
peak resident size, so the estimate is an upper bound (``tests/engine/test_hostile_input.py``
checks it against a bake's traced peak).
"""
from .reuse import PAIRS_PER_BLOCK
from .texels import MAX_CANDIDATES, RASTER_BYTES_PER_TEXEL, TEXEL_BYTES

#: Most independent batches per texel (for the standard error; the bake's, ``driver``).
MAX_BATCHES = 8
#: Largest (batches x texels x 3) float32 array of batch means an ObjectBake keeps
#: (``ObjectBake.batch_means``: the errors of a region's mean); larger bakes keep none.
BATCH_MEANS_BYTES = 64 << 20
#: Bytes of one block of path reuse's tile pairs in flight (``reuse.combine``: about 16
#: float32 arrays of a pair each, and their indices).
REUSE_BLOCK_BYTES = 96 * PAIRS_PER_BLOCK

#: Bytes kept per texel of a baked object: its texel and its value and standard error.
RESULT_BYTES_PER_TEXEL = TEXEL_BYTES + 2 * 3 * 4
#: Bytes kept per pixel of a baked object: its RGBA float32 image, and the Blender image.
RESULT_BYTES_PER_PIXEL = 16 + 16
#: Bytes per texel while it is traced: the sums of the batch means and their squares, its state.
TRACE_BYTES_PER_TEXEL = 2 * 3 * 8 + 8
#: Bytes per texel while its statistics are formed: the two sums and a temporary.
STATISTICS_BYTES_PER_TEXEL = 3 * 3 * 8
#: Bytes per pixel while the image is formed: the values as an image (12), the dilation's
#: float64 copy (24) and masks.
FINISH_BYTES_PER_PIXEL = 12 + 24 + 4
#: Bytes per path of a work unit in flight (the wavefront's arrays and their temporaries).
PATH_BYTES = 1536
#: Bytes per candidate of a rasterisation chunk.
CANDIDATE_BYTES = 128
#: Bytes per scene triangle: the tracer's BVH (embree) and per-triangle tables.
TRIANGLE_BYTES = 1024
#: Fixed overhead of a bake (bytes).
FIXED_BYTES = 64 * 1024 ** 2


def estimate_bake_bytes(texel_counts, resolution, samples, n_triangles, threads, paths_per_unit):
    """Peak memory of a bake (bytes, module docstring) of objects with ``texel_counts`` texels
    each at ``resolution`` (one side for all, or one per object) and ``samples`` paths per texel, in a scene of ``n_triangles``, with
    ``threads`` work units of at most ``paths_per_unit`` paths in flight."""
    counts = [int(n) for n in texel_counts]
    sides = [int(r) for r in resolution] if hasattr(resolution, "__len__") else [int(resolution)] * len(counts)
    pixels = max(sides, default=0) ** 2
    batches = batch_count(max(int(samples), 1))
    kept = sum(RESULT_BYTES_PER_TEXEL * n + RESULT_BYTES_PER_PIXEL * r * r + batch_means_bytes(n, batches)
               for n, r in zip(counts, sides))
    n = max(counts, default=0)
    working = max(RASTER_BYTES_PER_TEXEL * n + CANDIDATE_BYTES * min(MAX_CANDIDATES, 4 * n + 1),
                  TRACE_BYTES_PER_TEXEL * n + int(threads) * (min(int(paths_per_unit), n * int(samples)) * PATH_BYTES
                                                              + REUSE_BLOCK_BYTES),
                  STATISTICS_BYTES_PER_TEXEL * n,
                  FINISH_BYTES_PER_PIXEL * pixels if counts else 0)
    return kept + working + TRIANGLE_BYTES * int(n_triangles) + FIXED_BYTES


def batch_count(samples):
    """Largest divisor of ``samples`` that is at most :data:`MAX_BATCHES`: the bake's batches."""
    samples = int(samples)
    return max(b for b in range(1, min(MAX_BATCHES, samples) + 1) if samples % b == 0)


def batch_means_bytes(n_texels, batches):
    """Bytes of the batch means an object of ``n_texels`` baked in ``batches`` keeps (0: none)."""
    size = int(batches) * int(n_texels) * 12
    return size if int(batches) > 1 and size <= BATCH_MEANS_BYTES else 0
