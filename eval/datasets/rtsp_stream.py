"""A real RTSP camera on loopback, for ``fr track``'s tests and measurements: Debian's
``rtsp-server-perl`` (package ``rtsp-server-perl``) serving a synthetic clip that ``ffmpeg``
(package ``ffmpeg``) publishes to it.

:func:`write_clip` renders frames of a :class:`~fr_eval.datasets.live_stream.SyntheticCamera`
(the synthetic room of :func:`fr_torch.synthetic.render_manhattan_room`, known focal length) and
has ffmpeg encode them as H.264 (a key frame every ``keyframe_every`` frames, so that a reader
that joins or rejoins decodes within a fraction of a second) in an MP4 file.

:class:`RTSPServer` starts ``rtsp-server-perl`` on free ports of 127.0.0.1 (its reader port,
``url``, and its publisher port) as a process of its own; :meth:`RTSPServer.publish` starts
``ffmpeg -re -stream_loop -1 -i CLIP -c copy -f rtsp`` pushing the clip to it at its frame rate,
endlessly (ANNOUNCE / RECORD), and :meth:`RTSPServer.stop_publisher` stops it: readers of the mount
then get no more packets, and a reader that opens the URL meanwhile gets ``404 Not Found``, until
the next :meth:`~RTSPServer.publish`.  :meth:`RTSPServer.close` (the end of a ``with`` block) ends
both processes and waits for them; none is left.

What this server does not do: authentication (its source says ``TODO: check auth``), so a
``user:password@`` in the URL is accepted and never checked; and RTP over TCP (interleaved), so
readers must ask for UDP, which OpenCV's FFmpeg does with
``OPENCV_FFMPEG_CAPTURE_OPTIONS=rtsp_transport;udp`` in the environment (:data:`READER_ENV`;
OpenCV's default is TCP).  RTP goes over UDP ports of 127.0.0.1 from a random even base.

:class:`AuthRTSPServer` is the server that checks a password: GStreamer's ``rtsp-server``
(``rtsp_auth_server.py`` beside this module, run by the system's Python) serving a clip to the
readers that give the right user and password (Basic authentication; the others get ``401
Unauthorized``), over TCP or UDP.

Run as a process::

    python -m fr_eval.datasets.rtsp_stream --fps 25     # prints its URL; CTRL-C ends it
    OPENCV_FFMPEG_CAPTURE_OPTIONS='rtsp_transport;udp' fr track rtsp://127.0.0.1:PORT/cam
"""
from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from fr_eval.datasets.live_stream import SyntheticCamera

#: The environment a reader of :class:`RTSPServer` needs: RTP over UDP (the server has no TCP).
READER_ENV = {"OPENCV_FFMPEG_CAPTURE_OPTIONS": "rtsp_transport;udp"}
SERVER = "rtsp-server-perl"
PACKAGES = ("rtsp-server-perl", "ffmpeg")  # the Debian packages of the server and the publisher
#: The script of :class:`AuthRTSPServer`, the Python that runs it and the Debian packages it needs.
AUTH_SERVER = Path(__file__).with_name("rtsp_auth_server.py")
SYSTEM_PYTHON = "/usr/bin/python3"
AUTH_PACKAGES = ("python3-gi", "gir1.2-gst-rtsp-server-1.0", "gstreamer1.0-plugins-good", "gstreamer1.0-plugins-bad")
_AUTH_PROBE = ("import gi; gi.require_version('Gst', '1.0'); gi.require_version('GstRtspServer', '1.0'); "
               "from gi.repository import Gst, GstRtspServer; Gst.init(None); "
               "missing = [n for n in ('filesrc', 'qtdemux', 'h264parse', 'rtph264pay') "
               "if not Gst.ElementFactory.find(n)]; assert not missing, missing")


def missing() -> str | None:
    """Why :class:`RTSPServer` cannot run here (a program not on PATH), or None."""
    absent = [name for name in (SERVER, "ffmpeg") if shutil.which(name) is None]
    if absent:
        return (f"{' and '.join(absent)} not found: apt-get install {' '.join(PACKAGES)} "
                "(an RTSP server and FFmpeg, to serve the synthetic camera over RTSP)")
    return None


def auth_missing() -> str | None:
    """Why :class:`AuthRTSPServer` cannot run here (GStreamer's RTSP server or the elements it
    uses not importable by the system's Python), or None."""
    try:
        probe = subprocess.run([SYSTEM_PYTHON, "-c", _AUTH_PROBE], capture_output=True, text=True, timeout=60)
    except OSError as exc:
        return f"{SYSTEM_PYTHON}: {exc}"
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["?"])[-1]
        return (f"GStreamer's RTSP server is not usable from {SYSTEM_PYTHON} ({last}): apt-get install "
                f"{' '.join(AUTH_PACKAGES)}")
    return None


def rtsp_url(port: int, name: str, user: str | None = None, password: str | None = None) -> str:
    """``rtsp://[user[:password]@]127.0.0.1:port/name``."""
    credentials = f"{user}:{password}@" if password is not None else f"{user}@" if user else ""
    return f"rtsp://{credentials}127.0.0.1:{port}/{name}"


def write_clip(path: str | Path, camera: SyntheticCamera, frames: int = 25, fps: float = 25.0,
               keyframe_every: int = 5) -> Path:
    """Frames 0 .. ``frames``-1 of ``camera`` encoded by ffmpeg as H.264 at ``fps`` frames per
    second in the MP4 file ``path`` (``keyframe_every`` frames between key frames); returns it."""
    path = Path(path)
    data = b"".join(camera.jpeg(k) for k in range(frames))
    subprocess.run(["ffmpeg", "-nostdin", "-hide_banner", "-loglevel", "error", "-y", "-f", "image2pipe",
                    "-framerate", f"{fps:g}", "-c:v", "mjpeg", "-i", "-", "-c:v", "libx264", "-preset", "ultrafast",
                    "-g", str(keyframe_every), "-pix_fmt", "yuv420p", str(path)],
                   input=data, check=True, capture_output=True, timeout=60)
    return path


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(0.2)
        return probe.connect_ex(("127.0.0.1", port)) == 0


def _end(process: subprocess.Popen | None) -> None:
    """End ``process`` (SIGTERM, then SIGKILL after 5 s) and wait for it."""
    if process is None or process.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 10.0)):
        try:
            process.send_signal(sig)
            process.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


class RTSPServer:
    """``rtsp-server-perl`` on 127.0.0.1 and an ffmpeg publisher of a clip (module docstring).

    ``name``: the mount (the URL's path); ``log``: a file for both programs' output (default: a
    temporary file, removed at :meth:`close`; :meth:`output` reads it).  Use as a context manager,
    or :meth:`start` and :meth:`close`."""

    def __init__(self, name: str = "cam", log: str | Path | None = None):
        reason = missing()
        if reason:
            raise FileNotFoundError(reason)
        self.name = name
        self.port, self.source_port = free_port(), free_port()
        # the server's UDP ports count up from it, 2 per stream; below Linux's ephemeral ports (32768-)
        self.rtp_port = 2 * random.randrange(5000, 16000)
        self._temporary_log = log is None
        if log is None:
            descriptor, log = tempfile.mkstemp(prefix="rtsp_server_", suffix=".log")
            os.close(descriptor)
        self._log_path = Path(log)
        self._log = open(self._log_path, "ab")
        self.server: subprocess.Popen | None = None
        self.publisher: subprocess.Popen | None = None

    def url(self, user: str | None = None, password: str | None = None) -> str:
        """The readers' URL, ``rtsp://[user[:password]@]127.0.0.1:PORT/name``."""
        return rtsp_url(self.port, self.name, user, password)

    def start(self, timeout_s: float = 20.0) -> RTSPServer:
        """Start the server and wait until it accepts connections on both ports (ended again if
        that fails or is interrupted)."""
        self.server = subprocess.Popen(
            [SERVER, "--clientport", str(self.port), "--serverport", str(self.source_port),
             "--client_listen_address", "127.0.0.1", "--source_listen_address", "127.0.0.1",
             "--rtp_start_port", str(self.rtp_port), "--loglevel", "2"],
            stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + timeout_s
            while not (_listening(self.port) and _listening(self.source_port)):
                if self.server.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"{SERVER} did not start: {self.output()[-500:]}")
                time.sleep(0.05)
        except BaseException:
            self.close()
            raise
        return self

    def publish(self, clip: str | Path, timeout_s: float = 20.0) -> None:
        """Start ffmpeg pushing ``clip`` to the mount at its frame rate, looping, and wait until
        the server has its stream (a reader's DESCRIBE succeeds)."""
        self.stop_publisher()
        self.publisher = subprocess.Popen(
            ["ffmpeg", "-nostdin", "-hide_banner", "-loglevel", "error", "-re", "-stream_loop", "-1",
             "-i", str(clip), "-c", "copy", "-f", "rtsp", f"rtsp://127.0.0.1:{self.source_port}/{self.name}"],
            stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout_s
        while not self.mounted():
            if self.publisher.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"ffmpeg could not publish {clip}: {self.output()[-500:]}")
            time.sleep(0.05)

    def mounted(self) -> bool:
        """Whether the mount has a stream: the server answers a DESCRIBE of it with 200."""
        request = (f"DESCRIBE {self.url()} RTSP/1.0\r\nCSeq: 1\r\nAccept: application/sdp\r\n\r\n").encode()
        try:
            with socket.create_connection(("127.0.0.1", self.port), timeout=2.0) as connection:
                connection.sendall(request)
                return connection.recv(64).startswith(b"RTSP/1.0 200")
        except OSError:
            return False

    def stop_publisher(self) -> None:
        """Stop the publisher (the camera goes away): ffmpeg ends its session (TEARDOWN), so the
        server drops the mount (a killed publisher would leave it mounted and block the next one);
        the server keeps running."""
        _end(self.publisher)
        self.publisher = None

    def output(self) -> str:
        """What the server and the publisher wrote so far."""
        self._log.flush()
        return self._log_path.read_text(errors="replace")

    def close(self) -> None:
        """End the publisher and the server and wait for them."""
        self.stop_publisher()
        _end(self.server)
        self.server = None
        if not self._log.closed:
            self._log.close()
            if self._temporary_log:
                self._log_path.unlink(missing_ok=True)

    def __enter__(self) -> RTSPServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class AuthRTSPServer:
    """GStreamer's RTSP server on 127.0.0.1 serving ``clip`` at ``/name`` to the readers that give
    ``user`` and ``password`` (module docstring); ``port`` once started.  The password goes to the
    server in a file readable by this user only, removed at :meth:`close`."""

    def __init__(self, clip: str | Path, user: str, password: str, name: str = "cam"):
        reason = auth_missing()
        if reason:
            raise FileNotFoundError(reason)
        self.clip, self.user, self.name = Path(clip), user, name
        descriptor, self._password_file = tempfile.mkstemp(prefix="rtsp_password_")
        with open(descriptor, "w") as file:
            file.write(password)
        self.port = 0
        self.process: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()  # the server's stderr

    def url(self, user: str | None = None, password: str | None = None) -> str:
        """A reader's URL, ``rtsp://[user[:password]@]127.0.0.1:PORT/name``."""
        return rtsp_url(self.port, self.name, user, password)

    def start(self, timeout_s: float = 30.0) -> AuthRTSPServer:
        """Start the server and wait for the port it listens on (ended again if that fails or is
        interrupted)."""
        self.process = subprocess.Popen(
            [SYSTEM_PYTHON, str(AUTH_SERVER), str(self.clip), "--user", self.user, "--password-file",
             self._password_file, "--mount", self.name],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self._log, text=True, start_new_session=True)
        try:
            port: list[str] = []
            reader = threading.Thread(target=lambda: port.append(self.process.stdout.readline()), daemon=True)
            reader.start()
            reader.join(timeout_s)
            if not port or not port[0].strip().isdigit():
                self._log.seek(0)
                raise RuntimeError(f"GStreamer's RTSP server did not start: "
                                   f"{self._log.read().decode(errors='replace')[-500:]}")
            self.port = int(port[0])
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """End the server, wait for it and remove the password file."""
        _end(self.process)
        if self.process is not None:
            self.process.stdout.close()
        self._log.close()
        Path(self._password_file).unlink(missing_ok=True)

    def __enter__(self) -> AuthRTSPServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.datasets.rtsp_stream", description=__doc__.split("\n")[0])
    parser.add_argument("--fps", type=float, default=25.0)
    parser.add_argument("--frames", type=int, default=50, help="frames of the clip, looped")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--name", default="cam", help="the mount: rtsp://127.0.0.1:PORT/NAME")
    args = parser.parse_args(argv)
    camera = SyntheticCamera(args.width, args.height)
    with tempfile.TemporaryDirectory() as folder, RTSPServer(args.name) as server:
        server.publish(write_clip(Path(folder) / "clip.mp4", camera, args.frames, args.fps))
        print(server.url(), flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
