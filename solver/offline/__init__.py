"""The offline stage (seed 002 §5, (5.31)–(5.34)): finite elements on the ball, the orthonormal basis,
the propagators over one observation interval, the jobs that solve them (locally or on Dask), and the
pipeline that assembles a model's offline arrays (:func:`yauyau.solver.offline.pipeline.precompute`).
Nothing heavy is imported until a builder runs."""
