"""A Foxglove WebSocket client for the tests (the `websockets` package: foxglove-sdk serves, it
has no client): it subscribes to every channel the server advertises and keeps what comes."""

import asyncio
import json
import struct
import time

import websockets

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01   # server binary opcode: subscription id u32, log time u64 (ns), payload


async def watch(port: int, proc, deadline: float) -> tuple[dict, dict]:
    """Subscribe to every channel as it is advertised; until the server goes (the flight ended).
    Returns the advertised channels by id and, per channel id, [(log_time_ns, payload), ...]."""
    while True:   # the view starts with the router, a few seconds before the services
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None)
            break
        except OSError:
            assert proc.poll() is None and time.monotonic() < deadline, "the live view never came up"
            await asyncio.sleep(0.2)
    channels, received, next_sub, sub_channel = {}, {}, 0, {}
    async with ws:
        while time.monotonic() < deadline:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=5.0)
            except asyncio.TimeoutError:
                if proc.poll() is not None:
                    break
                continue
            except websockets.ConnectionClosed:
                break
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    subs = []
                    for ch in op["channels"]:
                        channels[ch["id"]] = ch
                        sub_channel[next_sub] = ch["id"]
                        subs.append({"id": next_sub, "channelId": ch["id"]})
                        next_sub += 1
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif frame[0] == MESSAGE_DATA:
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                received.setdefault(sub_channel[sub], []).append((log_time, bytes(frame[13:])))
    return channels, received
