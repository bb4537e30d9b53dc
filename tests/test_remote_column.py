"""The acting policy is the exported policy (issue 61, item 3): `champion:focus-v2`, whose
moves after its first reading and whose stop are its posterior's, makes the same writes

* through the line protocol a program outside Python serves its column by (the recipe of
  docs/deploy.md, "Outside Python: what runs where": docs/examples/serve_column.py, a server
  with nothing but the standard library, run as its own process), as in-process;
* from its ONNX, TorchScript and safetensors exports, as itself;

over whole alignments, every write and every reading of the audit log the same. And
alignrl/apparatus/remote.py's driver says what is wrong with a column that answers badly."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

import pytest

from alignrl.apparatus.base import ApparatusError, NoEdgesError
from alignrl.apparatus.remote import RemoteColumn, serve_apparatus
from alignrl.cli.main import main

EXAMPLES = Path(__file__).resolve().parent.parent / "docs" / "examples"
CHAMPION = "champion:focus-v2"
REMOTE = "alignrl.apparatus.remote:RemoteColumn"
SEED = 3  # one whole alignment per parity check: the protocol's and each export's


def _calls(log: Path) -> list[tuple]:
    """What an alignment did to the column, in order: every write, reading and restore."""
    return [
        (record["event"], json.dumps(record.get("values"), sort_keys=True), record.get("width_px"))
        for record in map(json.loads, log.read_text().splitlines())
        if record["event"] in ("write", "measure", "read", "restore", "end")
    ]


def _align(policy: str, apparatus: str, args: dict, seed: int, log: Path, capsys) -> dict:
    argv = ["align", "--policy", policy, "--apparatus", apparatus, "--seed", str(seed)]
    argv += ["--apparatus-args", json.dumps(args), "--spec-px", "3.0", "--log", str(log)]
    if capsys is None:  # a module fixture: no capsys of its own
        with redirect_stdout(io.StringIO()) as out:
            code = main([*argv, "--json"])
        result = json.loads(out.getvalue())
    else:
        code = main([*argv, "--json"])
        result = json.loads(capsys.readouterr().out)
    assert code == result["exit_code"], result
    return result


@pytest.fixture(scope="module")
def champion_here(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """The champion's in-process alignment of seed SEED on the example's ToyColumn (its
    result and its audit log): what the line protocol and every export must reproduce. One
    alignment for the module: its posterior costs ~1.4 CPU-s each time it runs."""
    log = tmp_path_factory.mktemp("champion") / f"here-{SEED}.jsonl"
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(EXAMPLES))
        result = _align(CHAMPION, "serve_column:ToyColumn", {"seed": SEED}, SEED, log, None)
    return result, log


@contextmanager
def _served(seed: int) -> Iterator[int]:
    """docs/examples/serve_column.py as a consumer runs it: its own process, its port."""
    server = subprocess.Popen(
        [sys.executable, str(EXAMPLES / "serve_column.py"), "0", str(seed)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        yield int(server.stdout.readline().rsplit(":", 1)[1])
    finally:
        server.kill()
        server.wait()


def test_the_champion_acts_alike_through_the_line_protocol(
    champion_here: tuple[dict, Path], tmp_path: Path, capsys
) -> None:
    # `align` starts from wherever the column is: the seed's column here and there
    local, here = champion_here
    there = tmp_path / f"there-{SEED}.jsonl"
    with _served(SEED) as port:
        remote = _align(CHAMPION, REMOTE, {"port": port}, SEED, there, capsys)
    assert _calls(here) == _calls(there) and len(_calls(here)) > 6
    keys = ("outcome", "acquisitions", "final_width_px", "final_setting", "writes", "reason")
    assert {key: local[key] for key in keys} == {key: remote[key] for key in keys}
    assert local["outcome"] == "aligned"


@pytest.mark.parametrize("export_format", ["onnx", "torchscript", "safetensors"])
def test_every_export_of_the_champion_makes_its_writes(
    export_format: str, champion_here: tuple[dict, Path], tmp_path: Path, capsys, monkeypatch
) -> None:
    if export_format == "onnx":
        pytest.importorskip("onnxruntime")
    monkeypatch.syspath_prepend(str(EXAMPLES))
    out = tmp_path / export_format
    assert main(["export", CHAMPION, "--format", export_format, "--out", str(out)]) == 0
    capsys.readouterr()
    first, champion = champion_here
    exported = tmp_path / f"e-{SEED}.jsonl"
    then = _align(str(out), "serve_column:ToyColumn", {"seed": SEED}, SEED, exported, capsys)
    assert [call[0] for call in _calls(champion)] == [call[0] for call in _calls(exported)]
    assert (first["outcome"], first["writes"]) == (then["outcome"], then["writes"])
    if export_format == "onnx":  # ONNX Runtime's kernels: the same moves to ~1e-6 V
        assert _settings(exported) == pytest.approx(_settings(champion), abs=1e-4)
    else:  # the same network in torch: the same bits
        assert _calls(champion) == _calls(exported)


def _settings(log: Path) -> list[float]:
    """Every knob setting written and every width read, in order."""
    found = []
    for record in map(json.loads, log.read_text().splitlines()):
        found += [*(record.get("values") or {}).values()]
        found += [record["width_px"]] if record.get("width_px") is not None else []
    return found


class _Column:
    """A column served from Python: one lens, its readings scripted."""

    def __init__(self, widths: list[float | None]) -> None:
        self.knobs = {"defocus": (0.0, 10.0)}
        self.widths, self.setting = list(widths), 5.0

    def reset(self, seed=None) -> None:
        pass

    def read(self) -> dict[str, float]:
        return {"defocus": self.setting}

    def write(self, values) -> None:
        if not 0.0 <= values["defocus"] <= 10.0:
            raise ValueError(f"defocus {values['defocus']} outside [0, 10]")
        self.setting = values["defocus"]

    def measure(self) -> float:
        width = self.widths.pop(0)
        if width is None:
            raise NoEdgesError("no edges")
        return width

    def image(self) -> None:
        return None


def test_the_remote_driver_speaks_the_protocol() -> None:
    server, port = serve_apparatus(_Column([4.0, None]))
    try:
        column = RemoteColumn(port)
        assert column.knobs == {"defocus": (0.0, 10.0)} and column.read() == {"defocus": 5.0}
        column.write({"defocus": 7.5})
        assert column.read() == {"defocus": 7.5} and column.measure() == 4.0
        with pytest.raises(NoEdgesError):
            column.measure()  # a frame without edges: width_px null
        with pytest.raises(ValueError, match=r"refused write: defocus 11.0 outside \[0, 10\]"):
            column.write({"defocus": 11.0})  # a refused write is the protocol's ValueError
        assert column.read() == {"defocus": 7.5}
        column.close()
    finally:
        server.shutdown()
        server.server_close()


def _answering(replies: list[bytes]):
    """A server that answers every request with the next of `replies`, then hangs up."""
    import socketserver
    import threading

    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            for reply in replies:
                self.rfile.readline()
                self.wfile.write(reply)

    server = socketserver.TCPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, server.server_address[1]


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        (b"not json\n", "answered read with no JSON"),
        (b"[1, 2]\n", r"answered read with \[1, 2\]"),
        (b'{"ok": true}\n', "answered read without 'values'"),
        (b'{"values": {"defocus": "high"}}\n', "read defocus is 'high', no number"),
        (b'{"error": "vacuum interlock"}\n', "refused read: vacuum interlock"),
        (b'{"values": {"defocus": 1.0}}', "closed the connection or sent no whole line"),
    ],
)
def test_a_column_that_answers_badly_is_named(reply: bytes, message: str) -> None:
    server, port = _answering([reply])
    try:
        column = RemoteColumn(port, timeout_s=5.0)
        with pytest.raises(ApparatusError, match=message) as raised:
            column.read()
        assert f"127.0.0.1:{port}" in str(raised.value)
    finally:
        server.shutdown()
        server.server_close()


def test_align_names_a_column_nobody_serves(capsys, tmp_path: Path) -> None:
    server, port = _answering([])
    server.shutdown()
    server.server_close()  # the port is free again: nobody listens there
    argv = ["align", "--policy", CHAMPION, "--apparatus", REMOTE]
    code = main([*argv, "--apparatus-args", json.dumps({"port": port}), "--spec-px", "3"])
    error = capsys.readouterr().err
    assert code != 0 and f"cannot connect to the column at 127.0.0.1:{port}" in error
    assert "Traceback" not in error


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ({"port": 0}, "port must be an integer in 1-65535"),
        ({"port": 1, "timeout_s": 0}, "timeout_s"),
    ],
)
def test_the_remote_driver_refuses_bad_arguments(args: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        RemoteColumn(**args)
