"""cantools' half of the DBC round trip; crates/ihex-proto/tests/dbc.rs drives it and checks the results.

Reads a JSON request on stdin: {"dbc": path, "mask": int, "island_dbc": path,
"frames": [{"id": int, "data": hex, "values": {signal: physical value}, "island": bool}]}.
For every frame it decodes the data with the by-kind DBC (messages found through the frame-ID mask,
as `cantools decode --frame-id-mask` does), encodes the given values back to bytes with the same
message, and, for frames marked "island", decodes them again with the exact-ID island DBC.
Writes {"cantools": version, "results": [...]} to stdout. Both files load in cantools' strict mode,
and encoding is strict: every signal present and in range.
"""

import json
import sys

import cantools
from cantools.database.namedsignalvalue import NamedSignalValue


def signals(decoded):
    """Signal name -> {"value": number, "label": choice name or None}."""
    out = {}
    for name, value in decoded.items():
        if isinstance(value, NamedSignalValue):
            out[name] = {"value": value.value, "label": value.name}
        else:
            out[name] = {"value": value, "label": None}
    return out


def main():
    request = json.load(sys.stdin)
    by_kind = cantools.database.load_file(request["dbc"], frame_id_mask=request["mask"])
    island = cantools.database.load_file(request["island_dbc"])
    results = []
    for frame in request["frames"]:
        data = bytes.fromhex(frame["data"])
        message = by_kind.get_message_by_frame_id(frame["id"])
        result = {
            "name": message.name,
            "decoded": signals(message.decode(data)),
            "encoded": message.encode(frame["values"]).hex(),
        }
        if frame["island"]:
            exact = island.get_message_by_frame_id(frame["id"])
            result["island_name"] = exact.name
            result["island_decoded"] = signals(exact.decode(data))
        results.append(result)
    json.dump({"cantools": cantools.__version__, "results": results}, sys.stdout)


if __name__ == "__main__":
    main()
