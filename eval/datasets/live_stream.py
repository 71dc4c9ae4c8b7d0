"""A live camera with known calibration, for ``fr track``'s tests and measurements: synthetic
frames served at a fixed rate over HTTP (multipart MJPEG) or written to a pipe.

:class:`SyntheticCamera` is a fixed camera in one synthetic room
(:func:`fr_torch.synthetic.render_manhattan_room`) with a known focal length, whose pitch drifts
slowly (``drift_deg`` over ``drift_frames`` frames) and which may pan once (``pan_after`` frames,
to ``pan_to_deg``).  Frames are rendered once per distinct pose (the drift quantised to
``drift_step_deg``) without noise, then get fresh Gaussian image noise (``noise_sigma`` grey
levels) from ``noise_variants`` pre-drawn fields, and are JPEG-encoded once: serving costs no
rendering, so the source does not compete with the search for the CPU.  ``truth(k)`` is frame
k's camera.

:class:`MJPEGServer` serves a camera on ``http://127.0.0.1:PORT/stream.mjpg`` as
``multipart/x-mixed-replace`` at ``fps`` frames per second.  Frames follow the wall clock from
the server's start (frame ``k`` is due at ``start + k / fps``), as a camera's would: a client that
reconnects gets the current frame, not the first.  ``drop_after``: close each connection after
that many frames (a dropped stream).  :func:`write_frames` writes the same frames back to back to
a binary file (a pipe into ``fr track -``).

Run as a process (a source that can be killed)::

    python -m fr_eval.datasets.live_stream --port 8554 --fps 25 [--drift-deg 0.5 --drift-frames 15000]
    # prints its URL and the Unix time of frame 0
    python -m fr_eval.datasets.live_stream --stdout --fps 25 | fr track - --out track_pipe
"""
from __future__ import annotations

import argparse
import http.server
import sys
import threading
import time
from dataclasses import dataclass
from typing import BinaryIO

import cv2
import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import focal_from_hfov, rotation_from_angles
from fr_torch.synthetic import render_manhattan_room

BOUNDARY = b"frame"


@dataclass
class SyntheticCamera:
    """A fixed camera in one synthetic room (module docstring); angles in degrees, sizes in pixels."""

    width: int = 640
    height: int = 480
    hfov_deg: float = 70.0
    pan_deg: float = 20.0
    pitch_deg: float = 8.0
    roll_deg: float = 2.0
    drift_deg: float = 0.0  # pitch change over drift_frames (linear)
    drift_frames: int = 15000
    drift_step_deg: float = 0.01
    pan_after: int | None = None  # frame from which the camera looks at pan_to_deg
    pan_to_deg: float = 35.0
    noise_sigma: float = 3.0
    noise_variants: int = 4
    quality: int = 90
    room_seed: int = 0

    def __post_init__(self) -> None:
        self.focal_px = focal_from_hfov(self.hfov_deg, self.width)
        rng = np.random.default_rng(self.room_seed + 1)
        self._noise = [rng.normal(0, self.noise_sigma, (self.height, self.width)) for _ in range(self.noise_variants)]
        self._jpeg: dict[tuple[float, float, int], bytes] = {}

    def pose(self, k: int) -> tuple[float, float, float]:
        """(pan, pitch, roll) of frame ``k`` in degrees (the drift quantised as rendered)."""
        steps = round(self.drift_deg * min(k, self.drift_frames) / self.drift_frames / self.drift_step_deg) \
            if self.drift_deg else 0
        pan = self.pan_to_deg if self.pan_after is not None and k >= self.pan_after else self.pan_deg
        return pan, self.pitch_deg + steps * self.drift_step_deg, self.roll_deg

    def truth(self, k: int) -> Camera:
        """Frame ``k``'s camera (focal length, principal point at the centre, rotation)."""
        pan, pitch, roll = self.pose(k)
        return Camera(self.width, self.height, self.focal_px,
                      rotation=rotation_from_angles(pan, pitch, roll).numpy())

    def jpeg(self, k: int) -> bytes:
        """Frame ``k`` as a JPEG (cached per pose and noise field; bounded by the poses' count)."""
        pan, pitch, roll = self.pose(k)
        key = (pan, round(pitch, 6), k % self.noise_variants)
        if key not in self._jpeg:
            clean = render_manhattan_room(self.focal_px, self.truth(k).rotation, self.width, self.height,
                                          seed=self.room_seed, noise_sigma=0.0).astype(np.float64)
            image = np.clip(clean + self._noise[key[2]], 0, 255).astype(np.uint8)
            self._jpeg[key] = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])[1].tobytes()
        return self._jpeg[key]


class MJPEGServer:
    """``camera``'s frames as multipart MJPEG over HTTP on 127.0.0.1 (module docstring), served by
    threads of this process; ``url`` once started.  ``connections`` counts the clients served,
    ``sent`` the frames sent."""

    def __init__(self, camera: SyntheticCamera, fps: float = 25.0, port: int = 0, drop_after: int | None = None):
        self.camera, self.fps, self.drop_after = camera, float(fps), drop_after
        self.connections = self.sent = 0
        self.start_time = time.monotonic()
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                server.connections += 1
                self.send_response(200)
                self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY.decode()}")
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                count = 0
                try:
                    while server.drop_after is None or count < server.drop_after:
                        k = server.due_frame()
                        data = server.camera.jpeg(k)
                        self.wfile.write(b"--" + BOUNDARY + b"\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                         + str(len(data)).encode() + b"\r\n\r\n" + data + b"\r\n")
                        self.wfile.flush()
                        server.sent += 1
                        count += 1
                        time.sleep(max(0.0, server.start_time + (k + 1) / server.fps - time.monotonic()))
                except (BrokenPipeError, ConnectionResetError):
                    pass

            def log_message(self, *args):  # no access log on stderr
                pass

        self._http = http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self._http.daemon_threads = True
        self._thread = threading.Thread(target=self._http.serve_forever, name="mjpeg-server", daemon=True)

    def due_frame(self) -> int:
        """The frame due now: the wall clock since the start, in frames."""
        return int((time.monotonic() - self.start_time) * self.fps)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self._http.server_address[1]}/stream.mjpg"

    def start(self) -> MJPEGServer:
        self.start_time = time.monotonic()
        self._thread.start()
        return self

    def stop(self) -> None:
        self._http.shutdown()
        self._http.server_close()

    def __enter__(self) -> MJPEGServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def write_frames(out: BinaryIO, camera: SyntheticCamera, count: int, fps: float | None = None) -> None:
    """Write frames 0 .. count-1 of ``camera`` to ``out`` back to back (JPEG), at ``fps`` frames
    per second (None: as fast as ``out`` takes them)."""
    start = time.monotonic()
    for k in range(count):
        out.write(camera.jpeg(k))
        out.flush()
        if fps:
            time.sleep(max(0.0, start + (k + 1) / fps - time.monotonic()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.datasets.live_stream", description=__doc__.split("\n")[0])
    parser.add_argument("--port", type=int, default=8554)
    parser.add_argument("--stdout", action="store_true", help="write the frames to stdout instead of serving them")
    parser.add_argument("--frames", type=int, default=None, help="frames to write with --stdout (default: endless)")
    parser.add_argument("--fps", type=float, default=25.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--hfov", type=float, default=70.0)
    parser.add_argument("--drift-deg", type=float, default=0.0)
    parser.add_argument("--drift-frames", type=int, default=15000)
    parser.add_argument("--pan-after", type=int, default=None)
    parser.add_argument("--drop-after", type=int, default=None)
    args = parser.parse_args(argv)
    camera = SyntheticCamera(args.width, args.height, args.hfov, drift_deg=args.drift_deg,
                             drift_frames=args.drift_frames, pan_after=args.pan_after)
    if args.stdout:
        try:
            write_frames(sys.stdout.buffer, camera, args.frames or 2 ** 62, args.fps)
        except BrokenPipeError:
            return 0
        return 0
    server = MJPEGServer(camera, args.fps, args.port, args.drop_after).start()
    print(server.url, time.time() - (time.monotonic() - server.start_time), flush=True)  # URL, Unix time of frame 0
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
