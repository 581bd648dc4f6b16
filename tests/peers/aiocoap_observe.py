#!/usr/bin/env python3
"""Observe a resource with the aiocoap 0.4 library: the aiocoap observer of coapcam's
interop tests (crates/coapcam/tests/it/interop.rs).

Usage: aiocoap_observe.py URI COUNT

Prints the payload of the first response and of each notification, one per line
(prefixed by the Observe value: "OBSERVE PAYLOAD"), and exits 0 after COUNT
notifications; exits 1 if the observation ends or fails first.

Why not `aiocoap-client --observe`: in aiocoap 0.4.17 it cancels the observation as soon
as the first response arrives (cli/client.py, the `finally:` after
`await requester.response` calls `requester.observation.cancel()`), so it never prints a
notification, whatever the server (libcoap's /time included).
"""

import asyncio
import sys

import aiocoap


def show(message):
    payload = message.payload.decode("utf-8", "replace").strip()
    print(f"{message.opt.observe} {payload}", flush=True)


async def main():
    uri, count = sys.argv[1], int(sys.argv[2])
    context = await aiocoap.Context.create_client_context()
    request = aiocoap.Message(code=aiocoap.GET, uri=uri, observe=0)
    pending = context.request(request)
    first = await pending.response
    if not first.code.is_successful() or first.opt.observe is None:
        print(f"not observed: {first.code} {first.opt.observe}", file=sys.stderr)
        return 1
    show(first)
    seen = 0
    async for notification in pending.observation:
        show(notification)
        seen += 1
        if seen == count:
            pending.observation.cancel()
            return 0
    print(f"the observation ended after {seen} notifications", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
