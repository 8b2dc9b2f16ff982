"""Render docs/motions/<action>.png (one identity, 30 frames, 10 shown) and identities.png.

Run from the repository root: python bench/render_motions.py
"""

from pathlib import Path

import numpy as np

from aniformer.io.render import render_filmstrip
from aniformer.synth.bodies import BodyModel, sample_identities
from aniformer.synth.motions import ACTIONS, sample_motion

OUT = Path("docs/motions")


def main() -> None:
    body = BodyModel("notoes_collapse10pc")
    identity = sample_identities(1, seed=0)
    for action in ACTIONS:
        motion = sample_motion(action, seed=0, bone_labels=body.bone_labels, frames=30)
        vertices = body.pose(np.repeat(identity, 30, axis=0), motion.rotvecs, motion.translation)
        render_filmstrip([(action, vertices, body.faces)], OUT / f"{action}.png", frames=10)
    identities = sample_identities(8, seed=1)
    rest = body.pose(identities, np.zeros((8, len(body.bone_labels), 3), np.float32))
    render_filmstrip(
        [("8 sampled adults, rest pose", rest, body.faces)],
        OUT / "identities.png",
        frames=None,
        panel_px=150,
        view=(5, -75),
    )


if __name__ == "__main__":
    main()
