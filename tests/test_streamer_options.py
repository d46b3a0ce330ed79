"""`ServeOptions`: one typed, frozen value per `streamer serve`, the command line built from it, one default each."""

import inspect

import pytest
from pydantic import ValidationError

from streamer.cli import build_parser
from streamer.options import ServeError, ServeOptions
from streamer.record import RecordingSink
from streamer.sink import Sink
from streamer.vmc import VmcSink
from streamer.ws import WsServer


def parse(*flags: str) -> ServeOptions:
    args = build_parser().parse_args(["serve", *flags])
    return ServeOptions.parse(**{k: v for k, v in vars(args).items() if k in ServeOptions.model_fields})


def serve_flags() -> dict[str, str]:
    """{field name: flag} of every `streamer serve` option (not -h, -v)."""
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["serve"]
    return {a.dest: a.option_strings[-1] for a in sub._actions if a.dest not in ("help", "verbose")}


def test_every_flag_is_a_field_of_the_same_name_and_every_field_a_flag():
    flags = serve_flags()
    assert set(flags) == set(ServeOptions.model_fields)
    assert all(flag == "--" + name.replace("_", "-") for name, flag in flags.items())


def test_no_flags_give_the_options_defaults():
    assert parse() == ServeOptions()
    assert ServeOptions().root == "tether" and ServeOptions().max_sessions == 32 and ServeOptions().ws == ("127.0.0.1", 8765)


def test_flags_map_onto_their_fields():
    o = parse("--ws", "0.0.0.0:9000", "--vmc-root", "1,2,3", "--allow-origin", "http://a.example:3000",
              "--allow-origin", "*", "--http", "8080", "--max-sessions", "5", "--device", "3", "--root", "free")
    assert o.ws == ("0.0.0.0", 9000) and o.vmc_root == (1.0, 2.0, 3.0, 0.0) and o.http == (None, 8080)
    assert o.allow_origin == ("http://a.example:3000", "*") and o.max_sessions == 5 and o.root == "free"
    assert o.device_id == 3 and parse("--device", "USB").device_id == "USB"


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
])
def test_a_bad_option_is_one_message_naming_its_flag(values, message):
    with pytest.raises(ServeError) as e:
        ServeOptions.parse(**values)
    assert message in str(e.value)


def test_the_server_pieces_take_their_defaults_from_the_options():
    ws = inspect.signature(WsServer).parameters
    o = ServeOptions()
    assert ws["max_sessions"].default == o.max_sessions
    assert (ws["ping_interval"].default, ws["ping_timeout"].default) == (o.ping_interval, o.ping_timeout)


def test_websocket_vmc_and_recording_are_sinks(bundle, tmp_path):
    from streamer.pose import HumanoidRig, load_humanoid_map

    sk = bundle.skeleton
    rig = HumanoidRig.build(sk.names, sk.parents, sk.offsets, load_humanoid_map())
    for sink in (WsServer("127.0.0.1", 0, {}, None), VmcSink("127.0.0.1", 9, rig),
                 RecordingSink(tmp_path / "x.bvh", sk, bundle.feature_spec)):
        assert isinstance(sink, Sink), type(sink).__name__
        for name in ("open", "send", "close", "describe", "status"):
            ours, protocol = inspect.signature(getattr(sink, name)), inspect.signature(getattr(Sink, name))
            assert list(ours.parameters)[: len(protocol.parameters) - 1] == list(protocol.parameters)[1:], name
