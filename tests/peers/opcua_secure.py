"""An OPC UA client of our own script on asyncua (PyPI), for crates/coapcam/tests/it/opcua.rs:
against `coapcam serve --opcua URL --opcua-users FILE` (Basic256Sha256 SignAndEncrypt, user
names) it tries each way in and says what happened, one JSON object on a line of standard
output per attempt:

- `anonymous`: security mode None, no user (refused: the server offers no such endpoint);
- `secure`: Basic256Sha256 SignAndEncrypt with the client certificate of CERT_DIR (made
  there on the first run) as USER with PASSWORD; when it gets in, it reads the latest
  result's RecordId and calls MeasureNow.

    python3 opcua_secure.py opc.tcp://127.0.0.1:PORT TIMEOUT_S CERT_DIR USER PASSWORD
"""

import asyncio
import json
import socket
import sys
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

NAMESPACE = "urn:coapcam:station"
APP_URI = "urn:coapcam:test:opcua-secure"


def say(**fields):
    print(json.dumps(fields, default=str), flush=True)


async def anonymous(url, timeout):
    client = Client(url=url, timeout=timeout)
    try:
        async with client:
            return "connected"
    except Exception as e:  # noqa: BLE001 - what refused it is the answer
        return f"refused: {type(e).__name__}"


async def secure(url, timeout, cert_dir, user, password):
    key, cert = cert_dir / "client-key.pem", cert_dir / "client-cert.der"
    await setup_self_signed_certificate(
        key, cert, APP_URI, socket.gethostname(), [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": "coapcam-test-client"},
    )
    client = Client(url=url, timeout=timeout)
    client.application_uri = APP_URI
    client.set_user(user)
    client.set_password(password)
    await client.set_security(
        SecurityPolicyBasic256Sha256, str(cert), str(key),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )
    try:
        async with client:
            ns = await client.get_namespace_index(NAMESPACE)
            station = await client.nodes.objects.get_child([f"{ns}:Station"])
            latest = await station.get_child([f"{ns}:LatestResult", f"{ns}:RecordId"])
            before = await latest.read_value()
            method = await station.get_child([f"{ns}:MeasureNow"])
            record_id, outcome = await station.call_method(method)
            return {"in": True, "latest": before, "measure_now": [record_id, outcome]}
    except Exception as e:  # noqa: BLE001 - what refused it is the answer
        return {"in": False, "why": f"{type(e).__name__}: {e}"}


async def main(url, timeout, cert_dir, user, password):
    say(anonymous=await anonymous(url, timeout))
    say(secure=await secure(url, timeout, Path(cert_dir), user, password))


if __name__ == "__main__":
    try:
        asyncio.run(main(sys.argv[1], float(sys.argv[2]), *sys.argv[3:6]))
    except Exception as e:  # noqa: BLE001 - the test reads the reason
        print(f"opcua_secure.py: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
