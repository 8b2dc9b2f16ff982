"""AniFormer (BMVC 2021): data-driven 3D mesh animation with a transformer, in pure PyTorch."""

__all__ = ["AniFormer", "AniFormerConfig"]


def __getattr__(name: str):
    # the model (and torch) load on first use, so `import aniformer.io.mesh` and a job's --help stay light
    if name in __all__:
        from aniformer import model

        return getattr(model, name)
    raise AttributeError(f"module 'aniformer' has no attribute {name!r}")
