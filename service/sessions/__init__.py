"""Filtering sessions: chunks of rows applied exactly once to a stored filter state, micro-batched per
model, and the responses they make (what the HTTP routes call; no HTTP here)."""
