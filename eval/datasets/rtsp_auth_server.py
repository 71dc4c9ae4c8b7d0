"""An RTSP server that asks for a password: GStreamer's ``rtsp-server`` (Debian packages
``gir1.2-gst-rtsp-server-1.0``, ``gstreamer1.0-plugins-good``, ``python3-gi``) serving an H.264 MP4
clip on 127.0.0.1 to the readers that give ``user`` and ``password`` (HTTP Basic authentication,
RFC 2617; the others get ``401 Unauthorized``), over RTP on TCP or UDP.

A script for the system's Python (``/usr/bin/python3``, where ``gi`` lives), started by
:class:`fr_eval.datasets.rtsp_stream.AuthRTSPServer`; it imports nothing of fR.  Each reader gets
the clip from its start, at its frame rate, and the end of the clip ends the reader's stream.  It
prints the port it listens on, then serves until SIGTERM or SIGINT::

    /usr/bin/python3 eval/datasets/rtsp_auth_server.py CLIP --user viewer --password-file FILE
    # prints PORT; readers open rtsp://viewer:PASSWORD@127.0.0.1:PORT/cam

The password is read from a file (``--password-file``), so that it is not on the command line.
"""
import argparse
import signal
import sys

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402 (after the versions are required)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("clip", help="an MP4 file of H.264 video")
    parser.add_argument("--user", required=True)
    parser.add_argument("--password-file", required=True)
    parser.add_argument("--mount", default="cam", help="the URL's path")
    parser.add_argument("--port", type=int, default=0, help="0: any free port (printed)")
    args = parser.parse_args(argv)
    with open(args.password_file) as file:
        password = file.read().strip()
    Gst.init(None)
    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(args.port))

    auth = GstRtspServer.RTSPAuth()
    token = GstRtspServer.RTSPToken()
    token.set_string("media.factory.role", "viewer")
    auth.add_basic(GstRtspServer.RTSPAuth.make_basic(args.user, password), token)
    server.set_auth(auth)

    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(f'( filesrc location="{args.clip}" ! qtdemux ! h264parse ! '
                       'rtph264pay name=pay0 pt=96 config-interval=1 )')
    permissions = GstRtspServer.RTSPPermissions()
    permissions.add_role("viewer")
    permissions.add_permission_for_role("viewer", "media.factory.access", True)
    permissions.add_permission_for_role("viewer", "media.factory.construct", True)
    factory.set_permissions(permissions)
    server.get_mount_points().add_factory(f"/{args.mount}", factory)

    loop = GLib.MainLoop()
    if server.attach(None) == 0:
        print(f"cannot listen on 127.0.0.1:{args.port}", file=sys.stderr)
        return 1
    for sig in (signal.SIGTERM, signal.SIGINT):
        GLib.unix_signal_add(GLib.PRIORITY_DEFAULT, sig, loop.quit)
    print(server.get_bound_port(), flush=True)
    loop.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
