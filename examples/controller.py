#!/usr/bin/env python3
"""A controller for microstereo's manipulator bridge, with no dependencies: it sends the
pipette into a cell, back out and home, as many times as asked.

    python3 examples/controller.py [HOST:PORT] [--times N] [--track ID]

Cells are named by their track: one id per physical cell for as long as it is seen (the
default graph's track node). A bridge fed by triangulate directly names them by their index
in each frame instead (scene lines without "ids": "track"), which the controller then uses.

The bridge sends one JSON object per line (every frame's scene, and the events of the moves);
the controller sends one command per line. Events are read from a file opened for reading
only and commands written on the socket itself: one text file for both directions
(`makefile("rw")`) throws away what it had read ahead whenever it writes, which loses
events and cuts lines in two.
"""

import json
import socket
import sys


def main(argv):
    addr, times, cell = "127.0.0.1:7878", 1, None
    args = iter(argv)
    for a in args:
        if a == "--times":
            times = int(next(args))
        elif a in ("--track", "--cell"):
            cell = int(next(args))
        else:
            addr = a
    host, port = addr.rsplit(":", 1)
    sock = socket.create_connection((host, int(port)))
    events = (json.loads(line) for line in sock.makefile("r", encoding="utf-8", newline="\n"))

    def send(**cmd):
        sock.sendall((json.dumps(cmd) + "\n").encode())

    def until(*kinds):
        """The next event of one of these kinds (scenes and progress go by)."""
        for ev in events:
            if ev["event"] in kinds:
                return ev
        raise SystemExit("the bridge closed the connection")

    arrived = 0
    tried = set()
    while arrived < times:
        scene = until("scene")
        by_track = scene.get("ids") == "track"
        key = "track" if by_track else "cell"
        # Cells whose height is trusted are the ones the bridge sends the pipette into;
        # with tracks, those confirmed and seen in this frame.
        ready = {t["id"] for t in scene.get("tracks", []) if t["state"] == "confirmed" and t["missed"] == 0}
        ids = [c["id"] for c in scene["cells"] if c["quality"]["trusted"] and (not by_track or c["id"] in ready)]
        if cell is not None:
            ids = [cell]
        fresh = [i for i in ids if i not in tried] or ids
        if not fresh:
            continue
        target = fresh[0]
        send(cmd="approach", **{key: target})
        ev = until("plan", "blocked", "error")
        if ev["event"] != "plan":
            # No way in to that cell now (walled in by others, say): another one.
            print(f"{key} {target}: {ev.get('reason') or ev.get('message')}", flush=True)
            tried.add(target)
            continue
        ev = until("arrived", "blocked", "error", "stopped")
        if ev["event"] != "arrived":
            print(f"approach to {key} {target} ended: {ev}", flush=True)
            return 1
        print(f"in {key} {target}, tip at {ev['tip']} (error {ev['error_um']:.2f} um)", flush=True)
        arrived += 1
        # Out along the axis, then home: the next approach starts from rest, clear of
        # every cell.
        for cmd in ("retract", "home"):
            send(cmd=cmd)
            ev = until("arrived", "blocked", "error", "stopped")
            if ev["event"] != "arrived":
                print(f"{cmd} ended: {ev}", flush=True)
                return 1
        tried.add(target)
    print(f"{arrived} of {times} approaches arrived", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
