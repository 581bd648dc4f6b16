"""An OPC UA client of our own script on asyncua (PyPI), a library we did not write, for
crates/coapcam/tests/it/opcua.rs: against `coapcam serve --opcua URL` it browses the
Objects folder and the station, reads its identity, its cameras and the latest result with
its photo, subscribes to the station's events (NewResultEventType's fields), calls
MeasureNow and waits for the event of the record it made, reads the latest result and its
photo again, then reads the records by id (GetResultById) and by id and time
(GetResultsSince). Each step is one JSON object on a line of standard output; any failure
exits non-zero with the reason on standard error.

    python3 opcua_client.py opc.tcp://127.0.0.1:PORT TIMEOUT_S
"""

import asyncio
import datetime
import hashlib
import json
import sys
import time

from asyncua import Client, ua

NAMESPACE = "urn:coapcam:station"


def say(**fields):
    print(json.dumps(fields, default=str), flush=True)


def unix_ms(t):
    """Milliseconds since 1970 of an asyncua time (UTC, naive or aware)."""
    if t.tzinfo is None:
        t = t.replace(tzinfo=datetime.timezone.utc)
    return t.timestamp() * 1000.0


def plain(value):
    """A value as JSON takes it."""
    if isinstance(value, datetime.datetime):
        return unix_ms(value)
    if isinstance(value, list):
        return [plain(v) for v in value]
    return value


class Events:
    """Puts each event into a queue, with when it arrived."""

    def __init__(self):
        self.queue = asyncio.Queue()

    def event_notification(self, event):
        self.queue.put_nowait((time.time() * 1000.0, event))


async def names(node):
    return [(await c.read_browse_name()).Name for c in await node.get_children()]


async def main(url, timeout):
    async with Client(url=url, timeout=timeout) as client:
        ns = await client.get_namespace_index(NAMESPACE)
        objects = client.nodes.objects
        station = await objects.get_child([f"{ns}:Station"])
        latest = await station.get_child([f"{ns}:LatestResult"])
        identity = await station.get_child([f"{ns}:Identity"])
        say(
            browse={
                "Objects": await names(objects),
                "Station": await names(station),
                "Identity": await names(identity),
                "LatestResult": await names(latest),
            },
            display_name=(await station.read_display_name()).Text,
        )

        async def read(node, leave=()):
            out = {}
            for child in await node.get_children():
                name = (await child.read_browse_name()).Name
                if name not in leave:
                    out[name] = plain(await child.read_value())
            return out

        photo_node = await latest.get_child([f"{ns}:Photo"])

        async def photo():
            """The latest result's photo: its size, SHA-256 and first bytes."""
            jpeg = await photo_node.read_value()
            if jpeg is None:
                return None
            return {"bytes": len(jpeg), "sha256": hashlib.sha256(jpeg).hexdigest(),
                    "head": jpeg[:2].hex()}

        say(identity=await read(identity))
        cameras = await station.get_child([f"{ns}:Cameras"])
        say(cameras={(await c.read_browse_name()).Name: await read(c)
                     for c in await cameras.get_children()})
        say(latest=await read(latest, leave=("Photo",)), photo=await photo())

        events = Events()
        subscription = await client.create_subscription(100, events)
        # The fields of NewResultEventType, without a where clause: async-opcua 0.19's
        # event filters do not compare node ids (InList on EventType never matches), and
        # every event of Station is of that type.
        event_type = client.get_node(ua.NodeId("NewResultEventType", ns))
        await subscription.subscribe_events(station, event_type, where_clause_generation=False)
        method = await station.get_child([f"{ns}:MeasureNow"])
        record_id, outcome = await station.call_method(method)
        say(measure_now={"record_id": record_id, "outcome": outcome})
        while True:
            arrived, event = await asyncio.wait_for(events.queue.get(), timeout)
            fields = event.get_event_props_as_fields_dict()
            message = fields["Message"].Value.Text
            say(
                event={
                    "message": message,
                    "source_name": fields["SourceName"].Value,
                    "time_unix_ms": unix_ms(fields["Time"].Value),
                    "arrived_unix_ms": arrived,
                    "event_type": fields["EventType"].Value.Identifier,
                    "fields": {
                        name: plain(fields[name].Value)
                        for name in ("RecordId", "LengthMm", "WidthMm", "HeightMm", "Status", "Codes")
                        if name in fields
                    },
                }
            )
            if message.startswith(f"record {record_id}"):
                break
        say(latest=await read(latest, leave=("Photo",)), photo=await photo())
        await subscription.delete()

        # Results by id and by time, from the station's log.
        by_id = await station.get_child([f"{ns}:GetResultById"])
        since = await station.get_child([f"{ns}:GetResultsSince"])
        fields = ("RecordId", "Time", "LengthMm", "WidthMm", "HeightMm", "DivisionMm",
                  "Shape", "Codes", "Status", "Trigger")
        answers = {}
        for record in (1, record_id):
            values = await station.call_method(by_id, ua.Variant(record, ua.VariantType.UInt64))
            answers[record] = dict(zip(fields, values))
        say(result_by_id={str(r): {k: plain(v) for k, v in a.items()} for r, a in answers.items()})
        try:
            await station.call_method(by_id, ua.Variant(999999, ua.VariantType.UInt64))
            say(result_by_id_missing="found")
        except ua.UaStatusCodeError as e:
            say(result_by_id_missing=type(e).__name__)

        any_time = datetime.datetime(1601, 1, 1)
        queries = {
            "all": (0, any_time, 0),
            "first_only": (0, any_time, 1),
            "after_1": (1, any_time, 10),
            "since_the_second": (0, answers[record_id]["Time"], 10),
            "after_the_last": (record_id, any_time, 10),
        }
        out = {}
        for name, (after, at, most) in queries.items():
            ids, times, lengths, widths, heights, statuses = await station.call_method(
                since,
                ua.Variant(after, ua.VariantType.UInt64),
                ua.Variant(at, ua.VariantType.DateTime),
                ua.Variant(most, ua.VariantType.UInt32),
            )
            out[name] = {
                "RecordIds": ids, "Times": plain(times), "LengthMm": lengths,
                "WidthMm": widths, "HeightMm": heights, "Status": statuses,
            }
        say(results_since=out)


if __name__ == "__main__":
    try:
        asyncio.run(main(sys.argv[1], float(sys.argv[2])))
    except Exception as e:  # noqa: BLE001 - the test reads the reason
        print(f"opcua_client.py: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
