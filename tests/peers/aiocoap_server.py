#!/usr/bin/env python3
"""An aiocoap 0.4 server: the peer of coapcam's interop tests (crates/coapcam/tests/it/interop.rs).

Usage: aiocoap_server.py [BIG_FILE]

Binds 127.0.0.1 on a port PORT found free for UDP and TCP, with PORT + 3000 free for TCP
too: aiocoap binds UDP and CoAP over TCP (RFC 8323) on PORT and, when the `websockets`
package is importable, CoAP over WebSockets on PORT + 3000 (aiocoap's rule for an explicit
port: transports/ws.py). Prints "ready UDP TCP WS" (the ports it listens on; WS is "-"
without WebSockets) on standard output once it listens, and serves until it is killed:

  /big      GET: the bytes of BIG_FILE (read once at start; empty without it), block-wise.
  /store    GET: the body last stored (4.04 before any); PUT: stores the body (2.01 when
            nothing was stored, else 2.04), block-wise uploads reassembled by aiocoap;
            POST: stores the body too and answers 2.01 with Location-Path "store";
            DELETE: forgets it (2.02).
  /echo     POST: answers 2.04 with the request body.
  /counter  GET: a decimal counter, observable: it grows and is notified every 250 ms.
  /.well-known/core: aiocoap's WKCResource, filtering on rt=, href=, ... (RFC 6690 4.1).
"""

import asyncio
import random
import socket
import sys

import aiocoap
import aiocoap.resource as resource
from aiocoap.numbers.codes import Code
from aiocoap.numbers.contentformat import ContentFormat
from aiocoap.transports.tcp import TCPServer
from aiocoap.transports.udp6 import MessageInterfaceUDP6


class Big(resource.Resource):
    rt = "interop.big"
    ct = 42

    def __init__(self, body):
        super().__init__()
        self.body = body

    async def render_get(self, request):
        return aiocoap.Message(
            payload=self.body, content_format=ContentFormat.OCTETSTREAM
        )


class Store(resource.Resource):
    rt = "interop.store"

    def __init__(self):
        super().__init__()
        self.body = None

    async def render_get(self, request):
        if self.body is None:
            return aiocoap.Message(code=Code.NOT_FOUND, payload=b"nothing stored")
        return aiocoap.Message(
            payload=self.body, content_format=ContentFormat.OCTETSTREAM
        )

    async def render_put(self, request):
        created = self.body is None
        self.body = request.payload
        return aiocoap.Message(code=Code.CREATED if created else Code.CHANGED)

    async def render_post(self, request):
        self.body = request.payload
        return aiocoap.Message(code=Code.CREATED, location_path=("store",))

    async def render_delete(self, request):
        self.body = None
        return aiocoap.Message(code=Code.DELETED)


class Echo(resource.Resource):
    rt = "interop.echo"

    async def render_post(self, request):
        return aiocoap.Message(code=Code.CHANGED, payload=request.payload)


class Counter(resource.ObservableResource):
    rt = "interop.counter"
    ct = 0

    def __init__(self):
        super().__init__()
        self.count = 0

    async def tick(self):
        while True:
            await asyncio.sleep(0.25)
            self.count += 1
            self.updated_state()

    async def render_get(self, request):
        return aiocoap.Message(
            payload=str(self.count).encode(), content_format=ContentFormat.TEXT
        )


def udp_port(context):
    """The port the context's UDP transport was given."""
    for interface in context.request_interfaces:
        messages = getattr(interface.token_interface, "message_interface", None)
        if isinstance(messages, MessageInterfaceUDP6):
            return messages.transport.get_extra_info("socket").getsockname()[1]
    raise RuntimeError("aiocoap opened no UDP transport")


def stream_ports(context):
    """The TCP ports of the context's CoAP over TCP and WebSocket listeners (None without)."""
    tcp = ws = None
    for interface in context.request_interfaces:
        transport = getattr(interface, "token_interface", None)
        if isinstance(transport, TCPServer):
            tcp = transport.server.sockets[0].getsockname()[1]
        elif type(transport).__name__ == "WSPool" and transport._servers:
            ws = transport._servers[0].sockets[0].getsockname()[1]
    return tcp, ws


def free(kind, port):
    """Whether 127.0.0.1:port can be bound now with a socket of kind."""
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def pick_port():
    """A port free for UDP and TCP whose port + 3000 is free for TCP: aiocoap binds a
    port it is given on every transport (0 would put its TCP listener on 5683)."""
    for _ in range(200):
        port = random.randrange(20000, 60000)
        if (
            free(socket.SOCK_DGRAM, port)
            and free(socket.SOCK_STREAM, port)
            and free(socket.SOCK_STREAM, port + 3000)
        ):
            return port
    raise RuntimeError("no free port pair found in 200 tries")


async def main():
    body = b""
    if len(sys.argv) > 1:
        with open(sys.argv[1], "rb") as f:
            body = f.read()
    root = resource.Site()
    root.add_resource(
        [".well-known", "core"],
        resource.WKCResource(root.get_resources_as_linkheader, impl_info=None),
    )
    root.add_resource(["big"], Big(body))
    root.add_resource(["store"], Store())
    root.add_resource(["echo"], Echo())
    counter = Counter()
    root.add_resource(["counter"], counter)
    context = await aiocoap.Context.create_server_context(
        root, bind=("127.0.0.1", pick_port())
    )
    ticking = asyncio.ensure_future(counter.tick())
    tcp, ws = stream_ports(context)
    print(f"ready {udp_port(context)} {tcp} {ws or '-'}", flush=True)
    try:
        await asyncio.get_running_loop().create_future()
    finally:
        ticking.cancel()


if __name__ == "__main__":
    asyncio.run(main())
