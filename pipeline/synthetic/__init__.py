"""Synthetic captures with known truth: the procedural specimen, the renderer of
a whole capture (``synth``) with its options, and ``pipeline score``, which
compares a capture's outputs with that truth."""
