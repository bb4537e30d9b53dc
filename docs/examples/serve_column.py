"""A column served to `alignrl align` over TCP, with nothing but the standard library: what a
program outside Python (C++, LabVIEW, a vendor's scripting host) does to run a champion
exactly as alignrl runs it (docs/deploy.md, "Outside Python: what runs where").

The program owns the microscope; alignrl asks, one JSON line at a time, and the program
answers each with one line (the protocol: alignrl/apparatus/remote.py). The column here is a
stand-in, `ToyColumn`: a lens whose edge width follows a hyperbola around an optimum that
each reset moves. On a real instrument, its five methods call your microscope instead.

    python docs/examples/serve_column.py 5555 &
    alignrl align --policy champion:focus-v2 --apparatus alignrl.apparatus.remote:RemoteColumn \
        --apparatus-args '{"port": 5555}' --spec-px 3.0

The same class is an ordinary driver too (`--apparatus serve_column:ToyColumn` with
docs/examples on the Python path): tests/test_remote_column.py checks that a champion makes
the same writes through the line protocol as in-process.
"""

from __future__ import annotations

import json
import math
import random
import socketserver
import sys

LOW_V, HIGH_V = 0.0, 100.0  # the lens's interval, volts
BEST_PX, BLUR_PX_PER_V = 2.5, 0.6  # the edge width in focus, and how fast it grows


class ToyColumn:
    """One lens, edge widths from a hyperbola: sqrt(best^2 + (gain (v - optimum))^2) px."""

    def __init__(self, seed: int = 0) -> None:
        self.knobs = {"defocus": (LOW_V, HIGH_V)}
        self.reset(seed)

    def reset(self, seed: int | None = None) -> None:
        draw = random.Random(seed)
        self._optimum = draw.uniform(30.0, 70.0)
        self._setting = draw.uniform(LOW_V, HIGH_V)

    def read(self) -> dict[str, float]:
        return {"defocus": self._setting}

    def write(self, values: dict[str, float]) -> None:
        value = float(values["defocus"])
        if set(values) != {"defocus"} or not LOW_V <= value <= HIGH_V:
            raise ValueError(f"refused: {values} (defocus within [{LOW_V}, {HIGH_V}] V)")
        self._setting = value

    def measure(self) -> float:
        return math.hypot(BEST_PX, BLUR_PX_PER_V * (self._setting - self._optimum))

    def image(self) -> None:
        return None


def answer(column: ToyColumn, request: dict) -> dict:
    """One request of the protocol, answered by `column`."""
    call = request.get("call")
    try:
        if call == "knobs":
            return {"knobs": {name: list(pair) for name, pair in column.knobs.items()}}
        if call == "reset":
            column.reset(request.get("seed"))
            return {"ok": True}
        if call == "read":
            return {"values": column.read()}
        if call == "write":
            column.write(request["values"])
            return {"ok": True}
        if call == "measure":
            return {"width_px": column.measure()}  # None for a frame without edges
    except ValueError as error:
        return {"error": str(error)}
    return {"error": f"unknown call {call!r}"}


def serve(port: int = 5555, seed: int = 0) -> None:
    """Serve one ToyColumn(`seed`) on localhost:`port` (0: a free one), each connection on a
    thread of its own (one left open by an earlier run does not hold up the next), until
    killed."""
    column = ToyColumn(seed)

    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            for line in self.rfile:
                reply = answer(column, json.loads(line))
                self.wfile.write(json.dumps(reply).encode() + b"\n")

    with socketserver.ThreadingTCPServer(("127.0.0.1", port), Handler) as server:
        print(f"serving a column on 127.0.0.1:{server.server_address[1]}", flush=True)
        server.serve_forever()


if __name__ == "__main__":
    # python serve_column.py [PORT [SEED]]: which column the stand-in is (ToyColumn's seed)
    serve(*(int(argument) for argument in sys.argv[1:3]))
