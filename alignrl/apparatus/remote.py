"""A column served over TCP by any program: the driver that lets a stack outside Python run a
champion exactly as alignrl runs it (docs/deploy.md, "Outside Python: what runs where").

A champion is more than its network: from its second reading on, focus-v2's moves and its
stop are its posterior's (alignrl/envs/ending.py), which no ONNX graph holds. So a program in
C++, LabVIEW or anything else does not re-implement the policy: it serves its column, and
`alignrl align --policy POLICY --apparatus alignrl.apparatus.remote:RemoteColumn
--apparatus-args '{"port": 5555}'` drives it, through the same shield as any driver.

The protocol, one JSON object a line (UTF-8, newline-terminated), alignrl asking and the
column answering each request with one line before the next request:

    {"call": "knobs"}                         {"knobs": {"defocus": [0.0, 100.0]}}
    {"call": "reset", "seed": 3}              {"ok": true}           (seed may be null)
    {"call": "read"}                          {"values": {"defocus": 41.5}}
    {"call": "write", "values": {...}}        {"ok": true}
    {"call": "measure"}                       {"width_px": 3.1}      ({"width_px": null}:
                                                                      a frame without edges)

Any request may be answered {"error": "TEXT"}: a write refused (a value outside its
interval) raises ValueError, as the protocol asks of a driver; any other call's error is an
ApparatusError. Images do not travel (`image` is None). `serve_apparatus` is a column served
this way from Python (tests, and the reference a server in another language can be read
against).
"""

from __future__ import annotations

import json
import math
import socket
import socketserver
import threading
from collections.abc import Mapping
from typing import Any

from alignrl.apparatus.base import Apparatus, ApparatusError, NoEdgesError

__all__ = ["MAX_LINE_BYTES", "RemoteColumn", "serve_apparatus"]

MAX_LINE_BYTES = 1 << 20  # a reply longer than this is no answer of this protocol
CONNECT_TIMEOUT_S = 10.0


class RemoteColumn:
    """The Apparatus protocol over a TCP connection to `host`:`port` (module docstring).
    Every call waits at most `timeout_s` for its answer; the shield bounds it too."""

    def __init__(self, port: int, host: str = "127.0.0.1", timeout_s: float = 60.0) -> None:
        if not (isinstance(port, int) and 0 < port < 65536):
            raise ValueError(f"port must be an integer in 1-65535, got {port!r}")
        if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s <= 3600):
            raise ValueError(f"timeout_s must be in (0, 3600] seconds, got {timeout_s!r}")
        self.address = f"{host}:{port}"
        try:
            self._socket = socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
        except OSError as error:
            raise ApparatusError(
                f"cannot connect to the column at {self.address}: {error}"
            ) from None
        self._socket.settimeout(float(timeout_s))
        self._lines = self._socket.makefile("rb")

    @property
    def knobs(self) -> dict[str, tuple[float, float]]:
        knobs = self._ask({"call": "knobs"}, "knobs")
        if not isinstance(knobs, dict):
            raise ApparatusError(f"the column at {self.address} answered knobs with {knobs!r}")
        return {str(name): self._interval(name, pair) for name, pair in knobs.items()}

    def reset(self, seed: int | None = None) -> None:
        self._ask({"call": "reset", "seed": seed}, "ok")

    def read(self) -> dict[str, float]:
        values = self._ask({"call": "read"}, "values")
        if not isinstance(values, dict):
            raise ApparatusError(f"the column at {self.address} answered read with {values!r}")
        return {str(name): self._number(f"read {name}", value) for name, value in values.items()}

    def write(self, values: Mapping[str, float]) -> None:
        self._ask({"call": "write", "values": {k: float(v) for k, v in values.items()}}, "ok")

    def measure(self) -> float:
        width = self._ask({"call": "measure"}, "width_px")
        if width is None:
            raise NoEdgesError(f"the column at {self.address} found no edges")
        return self._number("measure", width)

    def image(self) -> None:
        return None

    def close(self) -> None:
        self._lines.close()
        self._socket.close()

    # --- the line protocol -----------------------------------------------------------------

    def _ask(self, request: dict[str, Any], key: str) -> Any:
        call = request["call"]
        try:
            self._socket.sendall(json.dumps(request).encode() + b"\n")
            line = self._lines.readline(MAX_LINE_BYTES + 1)
        except OSError as error:  # a timeout included
            raise ApparatusError(
                f"the column at {self.address} did not answer {call}: {error}"
            ) from None
        if not line.endswith(b"\n"):
            raise ApparatusError(
                f"the column at {self.address} closed the connection or sent no whole line "
                f"(at most {MAX_LINE_BYTES} bytes) in answer to {call}"
            )
        try:
            answer = json.loads(line)
        except (UnicodeDecodeError, ValueError):
            raise ApparatusError(
                f"the column at {self.address} answered {call} with no JSON: {line[:80]!r}"
            ) from None
        if not isinstance(answer, dict):
            raise ApparatusError(f"the column at {self.address} answered {call} with {answer!r}")
        if "error" in answer:
            text = f"the column at {self.address} refused {call}: {answer['error']}"
            raise ValueError(text) if call == "write" else ApparatusError(text)
        if key not in answer:
            raise ApparatusError(
                f"the column at {self.address} answered {call} without {key!r}: {answer!r}"
            )
        return answer[key]

    def _number(self, what: str, value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ApparatusError(f"the column at {self.address}: {what} is {value!r}, no number")
        return float(value)

    def _interval(self, name: Any, pair: Any) -> tuple[float, float]:
        if not (isinstance(pair, list) and len(pair) == 2):
            raise ApparatusError(
                f"the column at {self.address}: knob {name!r} has {pair!r}, not [low, high]"
            )
        return self._number(f"{name} low", pair[0]), self._number(f"{name} high", pair[1])


def _answer(apparatus: Apparatus, request: Any) -> dict[str, Any]:
    """One request of the protocol, answered by `apparatus`."""
    call = request.get("call") if isinstance(request, dict) else None
    try:
        if call == "knobs":
            return {"knobs": {name: list(pair) for name, pair in apparatus.knobs.items()}}
        if call == "reset":
            apparatus.reset(request.get("seed"))
            return {"ok": True}
        if call == "read":
            return {"values": apparatus.read()}
        if call == "write":
            apparatus.write(request["values"])
            return {"ok": True}
        if call == "measure":
            try:
                width = apparatus.measure()
            except NoEdgesError:
                return {"width_px": None}
            return {"width_px": width if math.isfinite(width) else None}
    except (ValueError, ApparatusError) as error:
        return {"error": str(error)}
    return {"error": f"unknown call {call!r}"}


def serve_apparatus(
    apparatus: Apparatus, host: str = "127.0.0.1", port: int = 0
) -> tuple[socketserver.TCPServer, int]:
    """Serve `apparatus` by the protocol on `host`:`port` (0: a free port) from a thread,
    each connection on a thread of its own; returns the server (`shutdown()` and
    `server_close()` end it) and its port."""

    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            for line in self.rfile:
                self.wfile.write(json.dumps(_answer(apparatus, json.loads(line))).encode() + b"\n")

    server = socketserver.ThreadingTCPServer((host, port), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, int(server.server_address[1])
