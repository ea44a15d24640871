"""The numba kernels of :mod:`inspection.grid`, which trust their callers.

The public entry points in :mod:`inspection.grid` validate the inputs.

Every kernel is compiled with ``cache=True``: a process pays the compile time
once per machine and later only loads them (see :func:`inspection.grid.warmup`).

- :mod:`.layout`: cell codes, region codes, the face record's columns;
- :mod:`.prefetch`: the cache-line prefetch intrinsic;
- :mod:`.face`: a point against one face (exact closest point, plane tests);
- :mod:`.walk`: the descent to the locally closest face, writing the answer;
- :mod:`.query`: the fast path through the grid;
- :mod:`.bvh`: the exact slow path through a bounding volume hierarchy;
- :mod:`.build`: the grid build (faces per block, node faces, cell codes).
"""
