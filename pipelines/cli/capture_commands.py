"""``radarseg capture`` (a DCA1000's UDP stream into a capture file, or frame by frame to a service stream) and
``radarseg capture replay`` (a capture file sent as that stream)."""

from __future__ import annotations

import argparse
import io
import json
import queue
import sys
import threading
import time
import urllib.error
import urllib.request
from typing import Any

import numpy as np

from radar.errors import UserError

BACKLOG_FRAMES = 32  # frames received but not yet written or posted; more are dropped and counted
BAD_FRAME_POLICIES = ("zero", "drop")
MAX_LISTED_BAD_FRAMES = 100  # bad frames named in the summary (all are counted)


def add_commands(sub: Any) -> None:
    """capture and capture replay."""
    cap = sub.add_parser("capture", help="receive a DCA1000's raw-data UDP stream: frames into a capture file (.bin) "
                                         "or posted to a service stream; `capture replay` sends a capture as one")
    cap.add_argument("--profile", help="the radar's profile file (frame size, [capture] format); required")
    cap.add_argument("--port", type=int, default=4098, help="UDP data port (the DCA1000's default 4098)")
    cap.add_argument("--host", default="0.0.0.0", help="address to listen on")
    cap.add_argument("--out", help="capture file to write (.bin: the frames' words back to back, adc_data.bin)")
    cap.add_argument("--post", metavar="URL", help="the service: each frame to a new stream (POST /v1/streams)")
    cap.add_argument("--api-key", help="the service's API key")
    cap.add_argument("--max-frames", type=int, default=100, help="stop after this many frames (default 100)")
    cap.add_argument("--max-seconds", type=float, default=60.0, help="stop after this long (default 60 s)")
    cap.add_argument("--idle-timeout", type=float, default=2.0, help="stop when no packet came for this long (s)")
    cap.add_argument("--start-timeout", type=float, default=30.0, help="give up without a first packet (s)")
    cap.add_argument("--buffer-bytes", type=int, default=8 << 20, help="socket receive buffer asked for")
    cap.add_argument("--bad-frames", choices=BAD_FRAME_POLICIES, default="zero",
                     help="a frame the ADC checks refuse (undecoded words, nothing but an offset): 'zero' writes it as "
                          "zeros (every frame keeps its place in --out) and posts nothing; 'drop' leaves it out; "
                          "either way it is counted and the capture goes on")
    cap.set_defaults(func=cmd_capture)
    cap_sub = cap.add_subparsers(dest="capture_command")
    rep = cap_sub.add_parser("replay", help="send a capture file (.bin) as a DCA1000 UDP stream")
    rep.add_argument("capture", help="DCA1000 adc_data.bin or mmWave Studio PREFIX_Raw_0.bin")
    rep.add_argument("--profile", required=True, dest="replay_profile", help="the radar's profile file")
    rep.add_argument("--rate", type=float, default=10.0, help="frames per second")
    rep.add_argument("--to", default="127.0.0.1:4098", help="HOST:PORT to send to")
    rep.add_argument("--frames", type=int, help="send at most this many frames (default: all)")
    rep.add_argument("--loop", type=int, default=1, help="send the capture this many times")
    rep.add_argument("--drop", default="", help="packet sequence numbers to leave out, comma-separated")
    rep.add_argument("--swap", default="", help="packets to send after their successor, comma-separated")
    rep.set_defaults(func=cmd_replay)


def _numbers(text: str, flag: str) -> list[int]:
    try:
        return [int(word) for word in text.split(",") if word.strip()]
    except ValueError:
        raise UserError(f"{flag} takes comma-separated packet numbers, got {text!r}") from None


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(f"--to takes HOST:PORT, got {text!r}")
    return host, int(port)


def cmd_replay(args: argparse.Namespace) -> int:
    from radar.profiles import get_profile
    from radar.ti.capture import Capture
    from radar.ti.replay import replay

    profile = get_profile(args.replay_profile)
    capture = Capture(args.capture, profile, partial="skip")
    count = len(capture) if args.frames is None else min(args.frames, len(capture))
    if count < 1 or args.loop < 1:
        raise UserError(f"nothing to send: {len(capture)} frames in the capture, --frames {args.frames}, "
                        f"--loop {args.loop}")
    frames = (capture.words(i % len(capture)).tobytes() for i in range(count * args.loop))
    stats = replay(frames, _address(args.to), rate_fps=args.rate, frame_bytes=capture.geometry.bytes,
                   drop=_numbers(args.drop, "--drop"), swap=_numbers(args.swap, "--swap"))
    print(json.dumps(stats.to_dict()))
    return 0


def _call(url: str, method: str, body: bytes | None, content_type: str | None, key: str | None) -> dict:
    headers = {"Content-Type": content_type} if content_type else {}
    if key:
        headers["X-API-Key"] = key
    request = urllib.request.Request(url, data=body, method=method, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=60) as answer:
            text = answer.read()
    except urllib.error.HTTPError as error:
        raise UserError(f"{method} {url}: {error.code} {error.read().decode(errors='replace')[:300]}") from None
    except urllib.error.URLError as error:
        raise UserError(f"{method} {url}: {error.reason}") from None
    return json.loads(text) if text else {}


class StreamPoster:
    """Each frame (sck layout) to ``POST /v1/streams/{id}/frames?seq=N&input=adc``; a lost frame is a gap in seq."""

    def __init__(self, base: str, key: str | None):
        self.base, self.key = base.rstrip("/"), key
        self.id = _call(f"{self.base}/v1/streams", "POST", b"{}", "application/json", key)["id"]

    def post(self, seq: int, adc_sck: np.ndarray) -> dict:
        buf = io.BytesIO()
        np.save(buf, adc_sck.astype(np.complex64), allow_pickle=False)
        return _call(f"{self.base}/v1/streams/{self.id}/frames?seq={seq}&input=adc&outputs=objects", "POST",
                     buf.getvalue(), "application/x-npy", self.key)

    def close(self) -> None:
        _call(f"{self.base}/v1/streams/{self.id}", "DELETE", None, None, self.key)


def cmd_capture(args: argparse.Namespace) -> int:
    from radar.adc import ti_to_sck
    from radar.adc_checks import AdcCheckError, check_adc
    from radar.profiles import get_profile
    from radar.ti.dca1000 import CaptureFormat, FrameGeometry, decode_frame
    from radar.ti.live import open_data_socket, receive_frames
    from radar.ti.udp import FrameAssembler

    if args.profile is None:
        raise UserError("capture needs --profile PROFILE (the radar's frame size and capture format)")
    if args.out is None and args.post is None:
        raise UserError("say where the frames go: --out CAPTURE.bin and/or --post URL")
    if args.out is not None and not args.out.endswith(".bin"):
        raise UserError(f"--out takes a capture file name ending in .bin, got {args.out!r}")
    if args.max_frames < 1 or args.max_seconds <= 0:
        raise UserError("--max-frames must be >= 1 and --max-seconds > 0")
    profile = get_profile(args.profile)
    fmt = CaptureFormat.of_profile(profile)
    geometry = FrameGeometry.of_profile(profile, fmt)
    poster = StreamPoster(args.post, args.api_key) if args.post else None
    assembler = FrameAssembler(geometry.bytes)
    sock = open_data_socket(args.host, args.port, buffer_bytes=args.buffer_bytes)
    out = open(args.out, "wb") if args.out else None  # noqa: SIM115 (closed below)
    frames: queue.Queue = queue.Queue(maxsize=BACKLOG_FRAMES)  # receiving never waits on decoding, writing, posting
    backlog_drops = []

    def receive() -> None:
        try:
            for frame in receive_frames(sock, assembler, max_frames=args.max_frames, max_seconds=args.max_seconds,
                                        idle_timeout_s=args.idle_timeout, start_timeout_s=args.start_timeout):
                try:
                    frames.put_nowait(frame)
                except queue.Full:
                    backlog_drops.append(frame.index)
        finally:
            frames.put(None)

    start, first_index, posted = time.monotonic(), None, []
    print(f"listening on {args.host}:{sock.getsockname()[1]} for {geometry.bytes}-byte frames", file=sys.stderr)
    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    bad: list[int] = []
    try:
        while (frame := frames.get()) is not None:
            first_index = frame.index if first_index is None else first_index
            samples = decode_frame(np.frombuffer(frame.data, "<u2"), fmt, geometry)
            try:
                check_adc(samples, channel_axis=1, source=f"frame {frame.index - first_index}")
            except AdcCheckError as refused:  # one bad frame: flagged, counted, the capture goes on
                bad.append(frame.index - first_index)
                print(f"warning: {refused} ({'written as zeros' if args.bad_frames == 'zero' else 'dropped'})",
                      file=sys.stderr)
                if out is not None and args.bad_frames == "zero":
                    out.write(bytes(len(frame.data)))
                continue
            if out is not None:
                out.write(frame.data)
            if poster is not None:
                answer = poster.post(frame.index - first_index, ti_to_sck(samples, profile))
                posted.append(len(answer.get("objects", [])))
    finally:
        sock.close()
        if out is not None:
            out.close()
        if poster is not None:
            poster.close()
    seconds = time.monotonic() - start
    summary = {**assembler.stats.to_dict(), "frames_dropped_backlog": len(backlog_drops), "bad_frames": len(bad),
               "bad_frame_indices": bad[:MAX_LISTED_BAD_FRAMES], "bad_frame_policy": args.bad_frames,
               "seconds": round(seconds, 3), "out": args.out,
               "stream": poster.id if poster else None, "objects_per_frame": posted or None}
    print(json.dumps(summary))
    return 0
