"""AniFormer (BMVC 2021): data-driven 3D mesh animation with a transformer, in pure PyTorch."""

from aniformer.model import AniFormer, AniFormerConfig

__all__ = ["AniFormer", "AniFormerConfig"]
