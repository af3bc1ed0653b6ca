"""mfvs view: a Foxglove WebSocket client connects to the live server, subscribes to the camera and error
channels, and gets messages with the declared schemas; the shipped layout shows only channels the viewer has."""
import asyncio
import json
import struct
import threading
import time

import numpy as np
import websockets

from protocol import messages as m
from protocol.keys import Keys
from services.observe.foxglove_view import view_topics
from services.observe.view import HEALTH_TOPIC, Viewer
from services.runtime.transport import open_session
from tests.helpers import REPO

KEYS = Keys()
LAYOUT = REPO / "deploy" / "foxglove" / "mfvs.json"
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def frames(session, stop: threading.Event) -> None:
    """A camera and a vision at 20 Hz: a grey frame and the features found in it."""
    image_pub = session.declare_publisher(KEYS.camera_image)
    features_pub = session.declare_publisher(KEYS.features)
    k = 0
    while not stop.wait(0.05):
        header = m.Header(seq=k, stamp_ns=1_000_000_000 + k * 50_000_000)
        image_pub.put(m.encode(m.Image(header=header, width=64, height=48, encoding=m.ImageEncoding.MONO8,
                                       data=np.full(64 * 48, 100, np.uint8).tobytes())))
        features_pub.put(m.encode(m.Features(header=header, status=m.FeatureStatus.TARGET_LOST)))
        k += 1


async def client(port: int, topics: list[str], wanted: int) -> tuple[dict, dict]:
    """Connect, subscribe to ``topics`` and collect ``wanted`` messages of each: (advertised channels by topic,
    payloads by topic)."""
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        channels, received, subscribed = {}, {}, {}
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and not (
                subscribed and all(len(received.get(t, [])) >= wanted for t in topics)):
            raw = await asyncio.wait_for(ws.recv(), timeout=deadline - time.monotonic())
            if isinstance(raw, str):
                message = json.loads(raw)
                if message["op"] == "advertise":
                    channels.update({c["topic"]: c for c in message["channels"]})
                    new = [{"id": i, "channelId": channels[t]["id"]} for i, t in enumerate(topics)
                           if t in channels and t not in subscribed]
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                        subscribed.update({topics[s["id"]]: s["id"] for s in new})
            elif raw[0] == 0x01:  # message data: opcode, subscription id, receive time, payload
                subscription, _stamp = struct.unpack_from("<IQ", raw, 1)
                topic = next(t for t, i in subscribed.items() if i == subscription)
                received.setdefault(topic, []).append(raw[13:])
        return channels, received


def test_a_websocket_client_gets_the_camera_and_the_error_with_their_schemas(router):
    session = open_session(router.client_config())
    stop = threading.Event()
    try:
        with Viewer(session, KEYS, port=0) as viewer:
            threading.Thread(target=frames, args=(session, stop), daemon=True).start()
            channels, received = asyncio.run(client(viewer.port, ["/view/camera/image", "/view/features"], 3))
    finally:
        stop.set()
        session.close()
    assert channels["/view/camera/image"]["schemaName"] == "foxglove.CompressedImage"
    assert channels["/view/camera/image"]["encoding"] == "protobuf"
    assert channels["/view/features"]["schemaName"] == "mfvs.FeatureError"
    assert len(received["/view/camera/image"]) >= 3
    assert json.loads(received["/view/features"][0])["status"] == "target_lost"


def test_the_layout_shows_only_channels_the_viewer_has():
    layout = json.loads(LAYOUT.read_text())
    referenced = set()

    def walk(value):
        if isinstance(value, dict):
            for k, v in value.items():
                if k in ("imageTopic", "calibrationTopic", "topicPath"):
                    referenced.add(v)
                elif k == "value" and isinstance(v, str):
                    referenced.add(v.split(".", 1)[0])
                elif k in ("annotations", "topics"):
                    referenced.update(v)
                walk(v)
        elif isinstance(value, list):
            for v in value:
                walk(v)

    walk(layout["configById"])
    offered = view_topics() | {HEALTH_TOPIC}
    assert referenced and referenced <= offered, referenced - offered
    panels = set(layout["configById"])
    placed = set()

    def leaves(node):
        if isinstance(node, str):
            placed.add(node)
        else:
            leaves(node["first"])
            leaves(node["second"])

    leaves(layout["layout"])
    assert placed == panels
