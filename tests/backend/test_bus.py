"""Bus configuration and the typed request/reply helpers: private defaults, clear errors, no crash on bad input."""

from __future__ import annotations

import argparse
import json
import threading
import time

import pytest

from studio.backend import bus
from studio.backend import messages as msg

pytestmark = pytest.mark.timeout(60)


def parse(role: str, *argv: str) -> bus.BusConfig:
    p = argparse.ArgumentParser()
    bus.add_bus_arguments(p, role)
    return bus.bus_config_from_args(p.parse_args(list(argv)), role)


def test_defaults_are_loopback_only_without_multicast():
    hub = parse("hub")
    assert hub.mode == "router" and hub.listen == (bus.DEFAULT_HUB_ENDPOINT,) and hub.is_loopback_only
    worker = parse("worker")
    assert (
        worker.mode == "client" and worker.connect == (bus.DEFAULT_HUB_ENDPOINT,) and worker.is_loopback_only
    )
    for cfg in (hub, worker):
        z = cfg.zenoh_config()
        assert json.loads(z.get_json("scouting/multicast/enabled")) is False
        assert json.loads(z.get_json("transport/link/tx/lease")) == bus.LEASE_MS
        # What must arrive blocks a publisher for at most this long (µs) before Zenoh closes the full link.
        assert (
            json.loads(z.get_json("transport/link/tx/queue/congestion_control/block/wait_before_close"))
            == 5_000_000
        )
    # A peer without listen endpoints listens on loopback only (Zenoh's own default is every interface).
    peer = bus.BusConfig(mode="peer").zenoh_config()
    assert json.loads(peer.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]


def test_endpoints_choose_the_mode_and_round_trip_to_arguments():
    assert parse("worker", "--listen", "tcp/0.0.0.0:7448").mode == "peer"
    remote = parse("worker", "--connect", "tcp/10.0.0.5:7447")
    assert remote.mode == "client" and not remote.is_loopback_only
    assert parse("worker", *remote.to_args()) == remote
    multicast = parse("hub", "--multicast-scouting").zenoh_config().get_json("scouting/multicast/enabled")
    assert json.loads(multicast) is True


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"mode": "client"}, "needs at least one --connect"),
        ({"mode": "router"}, "needs a --listen"),
        (
            {"mode": "client", "connect": ("tcp/127.0.0.1:1",), "listen": ("tcp/127.0.0.1:2",)},
            "does not listen",
        ),
        ({"mode": "peer", "connect": ("127.0.0.1:7447",)}, "must look like"),
        ({"mode": "satellite"}, "bus mode"),
    ],
)
def test_bad_configurations_are_explained(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment):
        bus.BusConfig(**kwargs)


def test_client_without_a_hub_fails_with_a_clear_message():
    cfg = bus.BusConfig(
        mode="client", connect=(bus.loopback_endpoint(bus.free_loopback_port()),), connect_timeout_s=0.5
    )
    with pytest.raises(bus.BusError, match="is the hub"):
        bus.open_session(cfg)


@pytest.fixture
def pair(port):
    server = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    client = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    yield server, client
    client.close()
    server.close()


def test_queryable_answers_validates_and_survives_bad_input(pair):
    server, client = pair
    calls = []

    def handler(request, query):
        calls.append(request)
        if request.reason == "boom":
            raise RuntimeError("handler exploded")
        return msg.Ack(message=f"cancelled {request.job}")

    q = bus.declare_queryable(server, "test/rpc", handler, msg.JobCancel)
    assert bus.request(client, "test/rpc", msg.JobCancel(job="a"), msg.Ack).message == "cancelled a"
    with pytest.raises(bus.RemoteError, match="bad_request"):
        bus.request(client, "test/rpc", msg.Ack(), msg.Ack)  # well-formed, wrong type
    replies = list(client.get("test/rpc", payload=b"\x01\xc1\xc1", timeout=2))
    assert msg.decode(replies[0].ok.payload.to_bytes(), msg.ErrorReply).code == "bad_request"
    with pytest.raises(bus.RemoteError, match="internal: RuntimeError: handler exploded"):
        bus.request(client, "test/rpc", msg.JobCancel(job="b", reason="boom"), msg.Ack)
    # Still serving after all that.
    assert bus.request(client, "test/rpc", msg.JobCancel(job="c"), msg.Ack).message == "cancelled c"
    assert [c.job for c in calls] == ["a", "b", "c"]
    q.undeclare()
    with pytest.raises(bus.BusError, match="nobody answered"):
        bus.request(client, "test/rpc", msg.JobCancel(job="d"), msg.Ack, timeout=0.5)


def test_subscriber_drops_malformed_messages_and_keeps_going(pair):
    server, client = pair
    got = []
    done = threading.Event()

    def on(message, sample):
        got.append(message.seq)
        if message.seq == 2:
            done.set()

    sub = bus.declare_subscriber(server, "test/cmd", on, msg.EeTarget)
    pub = client.declare_publisher("test/cmd")
    time.sleep(0.3)
    pub.put(msg.encode(msg.EeTarget(seq=1, pos=(0, 0, 0), gripper=0)))
    pub.put(b"\x01garbage")
    pub.put(msg.encode(msg.Ack()))
    pub.put(b"")
    pub.put(msg.encode(msg.EeTarget(seq=2, pos=(0, 0, 0), gripper=1)))
    assert done.wait(5)
    assert got == [1, 2]
    sub.undeclare()


def test_latest_keeps_only_the_newest_value():
    box = bus.Latest()
    assert box.wait_until(lambda v: True, 0.05) is None
    for i in range(5):
        box.put(i)
    assert box.get() == (4, 5)
    threading.Timer(0.05, box.put, args=(10,)).start()
    assert box.wait_until(lambda v: v >= 10, 2.0) == 10


def test_a_stalled_subscriber_loses_samples_that_may_drop_but_none_that_must_arrive(port):
    """A consumer that stops reading fills the link's queue: Zenoh's default congestion control drops what a burst
    sends meanwhile; :data:`bus.MUST_ARRIVE` holds the publisher back until the consumer reads again."""
    hub = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    sender = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    receiver = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    burst, size = 200, 65536  # 13 MB: more than the loopback socket buffers hold
    try:
        got = {"drop": 0, "must": 0}
        sent = threading.Event()

        def receive_drop(_sample) -> None:
            if got["drop"] == 0:
                sent.wait(30)  # stalled until the whole burst was handed to the bus
            got["drop"] += 1

        def receive_must(_sample) -> None:
            if got["must"] == 0:
                time.sleep(0.5)  # (waiting for the burst here would wait forever: it blocks its sender)
            got["must"] += 1

        subs = [
            receiver.declare_subscriber("t/drop", receive_drop),
            receiver.declare_subscriber("t/must", receive_must),
        ]
        time.sleep(0.5)  # the subscriptions reach the sender
        for name, kwargs in (("drop", {}), ("must", {"congestion_control": bus.MUST_ARRIVE})):
            publisher = sender.declare_publisher(f"t/{name}", **kwargs)
            for _ in range(burst):
                publisher.put(bytes(size))
            sent.set()
            deadline = time.monotonic() + (10 if name == "must" else 2)  # a dropped sample never comes
            while got[name] < burst and time.monotonic() < deadline:
                time.sleep(0.05)
            publisher.undeclare()
        assert got["drop"] < burst, "the stall did not fill the queue: the test shows nothing"
        assert got["must"] == burst
        for sub in subs:
            sub.undeclare()
    finally:
        for s in (receiver, sender, hub):
            s.close()
