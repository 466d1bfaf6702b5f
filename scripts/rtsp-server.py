#!/usr/bin/env python3
"""Serve an H.264 MP4 file over RTSP, in real time, as an IP camera or a drone's video link does.

    python3 scripts/rtsp-server.py VIDEO.mp4 [PORT]     # rtsp://127.0.0.1:PORT/cam (default 8554)
    prl track --plan PLAN --video rtsp://127.0.0.1:8554/cam --live --init x,y,w,h --jsonl

A real RTSP server: GStreamer's gst-rtsp-server, from the OS's packages (Debian, Ubuntu):
    sudo apt-get install python3-gi gir1.2-gst-rtsp-server-1.0 gstreamer1.0-plugins-good gstreamer1.0-plugins-bad
(`.ci/run` installs them for tests/video.rs). Every client shares one stream; it ends when the
file does, so that the client sees the end of stream a camera switched off gives. Prints
`serving rtsp://127.0.0.1:PORT/cam` once it listens.
"""
import sys

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402

if len(sys.argv) not in (2, 3):
    sys.exit(__doc__)
path, port = sys.argv[1], sys.argv[2] if len(sys.argv) == 3 else "8554"
Gst.init(None)
server = GstRtspServer.RTSPServer.new()
server.set_address("127.0.0.1")
server.set_service(port)
factory = GstRtspServer.RTSPMediaFactory.new()
location = path.replace("\\", "\\\\").replace('"', '\\"')
factory.set_launch(f'( filesrc location="{location}" ! qtdemux ! h264parse ! rtph264pay name=pay0 pt=96 config-interval=1 )')
factory.set_shared(True)
server.get_mount_points().add_factory("/cam", factory)
if server.attach(None) == 0:
    sys.exit(f"rtsp-server: cannot listen on 127.0.0.1:{port}")
print(f"serving rtsp://127.0.0.1:{port}/cam", flush=True)
GLib.MainLoop().run()
