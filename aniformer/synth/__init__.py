"""Synthetic training data: Anny bodies (``bodies``) performing procedural actions (``motions``)."""
