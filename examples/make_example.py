"""Regenerate the bundled example image ``examples/room.png`` (rendered by our own code).

Camera: 640 x 480, f = 420 px (hfov 74.6 deg), pan 20, pitch 8, roll 4 deg (see fr_torch.core.geometry.conventions).
Run: ``python examples/make_example.py``.
"""
from pathlib import Path

import cv2

from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.synthetic import render_manhattan_room

FOCAL_PX, PAN, PITCH, ROLL = 420.0, 20.0, 8.0, 4.0

if __name__ == "__main__":
    rotation = rotation_from_angles(PAN, PITCH, ROLL).double().numpy()
    image = render_manhattan_room(FOCAL_PX, rotation, 640, 480, seed=3)
    out = Path(__file__).with_name("room.png")
    cv2.imwrite(str(out), image)
    print(f"wrote {out}")
