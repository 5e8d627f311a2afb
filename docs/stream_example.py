"""A client of the service's streams, with the standard library alone: open a stream, send the frames of one of the
service's example sequences in order, print each frame's objects with their track ids and velocity vectors and the
confirmed tracks at the end, close the stream.

    .venv/bin/radarseg serve            # in another terminal
    python docs/stream_example.py --url http://127.0.0.1:8000 --example 1 --frames 10

A radar of your own sends its cubes the same way: one POST per frame, ``?seq=`` counting up (a gap is coasted).
"""

from __future__ import annotations

import argparse
import json
import sys
import urllib.error
import urllib.request


def call(url: str, method: str = "GET", body: bytes | None = None, content_type: str | None = None,
         key: str | None = None) -> bytes:
    """One request; the service's error answer printed and raised as SystemExit on a 4xx/5xx."""
    headers = {"Content-Type": content_type} if content_type else {}
    if key:
        headers["X-API-Key"] = key
    request = urllib.request.Request(url, data=body, method=method, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=120) as answer:
            return answer.read()
    except urllib.error.HTTPError as error:
        raise SystemExit(f"{method} {url}: {error.code} {error.read().decode(errors='replace')}") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the service")
    parser.add_argument("--example", type=int, default=1, help="example sequence (GET /v1/examples)")
    parser.add_argument("--frames", type=int, default=10, help="frames to send (at most the example's)")
    parser.add_argument("--key", help="API key, when the service has keys")
    args = parser.parse_args(argv)
    base = args.url.rstrip("/")
    stream = json.loads(call(f"{base}/v1/streams", "POST", b"{}", "application/json", args.key))
    print(f"stream {stream['id']} on model {stream['model']}")
    try:
        for seq in range(args.frames):
            cube = call(f"{base}/v1/examples/{args.example}?frame={seq}", key=args.key)
            answer = json.loads(call(f"{base}/v1/streams/{stream['id']}/frames?seq={seq}&outputs=objects", "POST",
                                     cube, "application/x-npy", args.key))
            objects = ", ".join(f"#{o['track_id']} {o['class_name']} at ({o['x']:.1f}, {o['y']:.1f}) m moving "
                                f"({o['vx']:.1f}, {o['vy']:.1f}) m/s" for o in answer["objects"])
            print(f"frame {seq}: {objects or 'no object'}")
        shown = json.loads(call(f"{base}/v1/streams/{stream['id']}", key=args.key))
        for track in shown["tracks"]:
            print(f"track #{track['track_id']} {track['class_name']} ({track['status']}): {track['speed']:.1f} m/s "
                  f"heading {track['heading_deg']:.0f} deg, {track['hits']} hits in {track['age']} frames")
    finally:
        call(f"{base}/v1/streams/{stream['id']}", "DELETE", key=args.key)
    return 0


if __name__ == "__main__":
    sys.exit(main())
