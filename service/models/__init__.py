"""The models a worker serves: the loaded-model cache, precompute jobs added at run time, and the
analysis run in a process of its own."""
