"""`ServeOptions`: one typed, frozen value per `dimgestor serve`, the command line built from it, one default each."""

import inspect

import pytest
from pydantic import ValidationError

from dimgestor.cli_help import DeprecatedAlias
from dimgestor_app.cli import build_parser
from streamer.options import FLAGS, ServeError, ServeOptions, flag_of
from streamer.record import RecordingSink
from streamer.sink import Sink
from streamer.vmc import VmcSink
from streamer.ws import WsConfig, WsServer


def parse(*flags: str) -> ServeOptions:
    args = build_parser().parse_args(["serve", *flags])
    return ServeOptions.parse(**{k: v for k, v in vars(args).items() if k in ServeOptions.model_fields})


def serve_flags() -> dict[str, str]:
    """{field name: flag} of every `dimgestor serve` option (not -h, -v, nor the deprecated spellings)."""
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["serve"]
    return {a.dest: a.option_strings[-1] for a in sub._actions
            if a.dest not in ("help", "verbose") and not isinstance(a, DeprecatedAlias)}


def test_every_flag_is_a_field_of_the_same_name_and_every_field_a_flag():
    flags = serve_flags()
    assert set(flags) == set(ServeOptions.model_fields)
    assert all(flag == flag_of(name) for name, flag in flags.items())
    renamed = {name: flag for name, flag in flags.items() if flag != "--" + name.replace("_", "-")}
    assert renamed == FLAGS == {"osc": "--vmc", "device": "--input-device", "compute_device": "--device"}


def test_no_flags_give_the_options_defaults():
    assert parse() == ServeOptions()
    assert ServeOptions().root == "tether" and ServeOptions().max_sessions == 32 and ServeOptions().ws == ("127.0.0.1", 8765)


def test_flags_map_onto_their_fields():
    o = parse("--ws", "0.0.0.0:9000", "--vmc-root", "1,2,3", "--allow-origin", "http://a.example:3000",
              "--allow-origin", "*", "--http", "8080", "--max-sessions", "5", "--input-device", "3", "--root", "free",
              "--vmc", "127.0.0.1:39539")
    assert o.ws == ("0.0.0.0", 9000) and o.vmc_root == (1.0, 2.0, 3.0, 0.0) and o.http == (None, 8080)
    assert o.allow_origin == ("http://a.example:3000", "*") and o.max_sessions == 5 and o.root == "free"
    assert o.device_id == 3 and parse("--input-device", "USB").device_id == "USB" and o.osc == ("127.0.0.1", 39539)


def test_the_old_spellings_set_the_same_fields_and_say_once_what_replaced_them(capsys):
    assert parse("--osc", "127.0.0.1:39539") == parse("--vmc", "127.0.0.1:39539")
    err = capsys.readouterr().err.splitlines()
    assert err == ["dimgestor serve: --osc is now --vmc"]
    assert parse("--osc", "h:1", "--osc", "h:2").osc == ("h", 2)  # the last one wins, as for any option
    assert len(capsys.readouterr().err.splitlines()) == 1  # said once


def test_device_is_where_the_model_runs_and_a_microphone_given_to_it_points_to_input_device():
    """serve's --device was the microphone's (a deprecated spelling of --input-device): it is now the device the
    model runs on, and an index or a name that is no such device is refused with a one-line pointer."""
    assert parse().compute_device == "cpu"
    assert [parse("--device", d).compute_device for d in ("cpu", "cuda", "cuda:1")] == ["cpu", "cuda", "cuda:1"]
    for given in ("2", "USB Mic", "cuda:x", "gpu"):
        with pytest.raises(ServeError) as e:
            parse("--device", given)
        assert str(e.value) == (f"--device {given!r}: the device the model runs on (cpu, cuda or cuda:N); a "
                                f"microphone is --input-device (--input-device {given})")


def test_options_are_frozen_and_refuse_unknown_names():
    o = ServeOptions()
    with pytest.raises(ValidationError):
        o.window_ms = 100
    with pytest.raises(ServeError):
        ServeOptions.parse(windowms=100)


@pytest.mark.parametrize("values, message", [
    ({"window_ms": 5}, "--window-ms must be in 10..5000, got 5"),
    ({"ping_timeout": 0}, "--ping-timeout must be in (0, 3600], got 0"),
    ({"no_ws": True, "http": (None, 8080)}, "--http serves the viewer from the WebSocket server (drop --no-ws)"),
    ({"record": "x.bvh", "source": "ws"}, "--record records the server's own source"),
    ({"allow_origin": ["http://a.example/x"]}, "is not an origin"),
    ({"save_state_every": 5.0}, "--save-state-every saves sessions to the state store: give --state-store too"),
    ({"state_secret_file": "s"}, "--state-secret-file seals the states of the state store: give --state-store too"),
    ({"osc": ("127.0.0.1", 9), "vmc_max_bytes": 100}, "--vmc: "),  # named by its flag, not its field
    ({"osc": "nowhere"}, "--vmc: "),
])
def test_a_bad_option_is_one_message_naming_its_flag(values, message):
    with pytest.raises(ServeError) as e:
        ServeOptions.parse(**values)
    assert message in str(e.value)


def test_the_state_secret_comes_from_its_file_or_the_environment_and_only_with_a_store(tmp_path, monkeypatch):
    from streamer.redact import RedactTokens
    from streamer.server import read_state_secret

    monkeypatch.setattr(RedactTokens, "secrets", set())
    (tmp_path / "secret").write_text(" from the file\n")
    monkeypatch.setenv("DIMGESTOR_STATE_SECRET", "from the environment")
    store = {"state_store": "memory"}
    assert read_state_secret(ServeOptions(**store, state_secret_file=str(tmp_path / "secret"))) == b"from the file"
    assert read_state_secret(ServeOptions(**store)) == b"from the environment"
    assert read_state_secret(ServeOptions()) is None  # no store: nothing to seal
    assert {"from the file", "from the environment"} <= RedactTokens.secrets  # masked in every log line
    monkeypatch.delenv("DIMGESTOR_STATE_SECRET")
    assert read_state_secret(ServeOptions(**store)) is None
    (tmp_path / "empty").write_text("\n")
    for path, message in ((tmp_path / "empty", "is empty"), (tmp_path / "none", "No such file")):
        with pytest.raises(ServeError, match=f"--state-secret-file {path}: .*{message}|{message}"):
            read_state_secret(ServeOptions(**store, state_secret_file=str(path)))


def test_the_server_pieces_take_their_defaults_from_the_options():
    ws, o = WsConfig(), ServeOptions()
    assert ws.max_sessions == o.max_sessions
    assert (ws.ping_interval, ws.ping_timeout) == (o.ping_interval, o.ping_timeout)


def test_websocket_vmc_and_recording_are_sinks(bundle, tmp_path):
    from streamer.pose import HumanoidRig, load_humanoid_map

    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    for sink in (WsServer(WsConfig(), {}, None), VmcSink("127.0.0.1", 9, rig),
                 RecordingSink(tmp_path / "x.bvh", sk, bundle.feature_spec)):
        assert isinstance(sink, Sink), type(sink).__name__
        for name in ("open", "send", "close", "describe", "status"):
            ours, protocol = inspect.signature(getattr(sink, name)), inspect.signature(getattr(Sink, name))
            assert list(ours.parameters)[: len(protocol.parameters) - 1] == list(protocol.parameters)[1:], name
