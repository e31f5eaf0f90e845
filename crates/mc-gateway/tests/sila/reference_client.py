"""The reference SiLA 2 client (PyPI sila2) against the gateway's SiLA server; run by tests/sila.rs.

  reference_client.py definitions SILA_DIR
      Every feature definition of SILA_DIR/features validates against SILA_DIR/xsd's
      FeatureDefinition.xsd, and SiLA's own FDL-to-proto transform gives SILA_DIR/proto's files.
  reference_client.py first HOST SILA_PORT CA MQTT_PORT SILA_DIR NAME UUID
      The whole tour against a fresh demo gateway (its simulated island): found by mDNS by its UUID
      (and verified with the certificate its announcement carries), then over TLS trusting the
      certificate file CA; renames the server NAME.
  reference_client.py firmware HOST SILA_PORT CA MQTT_PORT SMALL BIG
      FirmwareUpdate and CancelController: uploads the image files SMALL and BIG over MQTT, updates
      111 and 112 with SMALL to its end, then starts BIG and cancels it.
  reference_client.py again HOST SILA_PORT CA UUID NAME
      After a restart: the same UUID and the name the first run gave.

Exits non-zero with the reason on the first thing that is not as it should be.
"""

import json
import os
import queue
import sys
import threading
import time
import traceback
import uuid
from pathlib import Path

WAIT = 20.0


def check(cond, what):
    if not cond:
        raise AssertionError(what)


def definitions(sila_dir: Path):
    from sila2.framework.utils import feature_definition_to_proto_string, parse_feature_definition

    features = sorted((sila_dir / "features").glob("*.sila.xml"))
    check(len(features) >= 2, f"no feature definitions in {sila_dir}")
    for fdl in features:
        # Validates against the FeatureDefinition.xsd inside sila2 (the same file as ours: compared below).
        node = parse_feature_definition(str(fdl))
        name = fdl.name.removesuffix(".sila.xml")
        proto = (sila_dir / "proto" / f"{name}.proto").read_text(encoding="utf-8")
        check(
            feature_definition_to_proto_string(node) == proto,
            f"proto/{name}.proto is not what SiLA's fdl2proto.xsl makes of features/{fdl.name}: regenerate it",
        )
        print(f"ok: {fdl.name} valid, proto/{name}.proto current")
    import sila2

    ours = (sila_dir / "xsd" / "FeatureDefinition.xsd").read_bytes()
    theirs = (Path(sila2.__file__).parent / "resources" / "xsd" / "FeatureDefinition.xsd").read_bytes()
    check(ours == theirs, "xsd/FeatureDefinition.xsd differs from the one sila2 validates with")


class Events:
    """The gateway's events topic and its retained node states, over MQTT."""

    def __init__(self, host, port):
        import paho.mqtt.client as mqtt

        self.q = queue.Queue()
        self.c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"sila-test-{uuid.uuid4().hex[:8]}")
        self.c.on_message = lambda c, u, m: self.q.put((m.topic, m.payload))
        self.c.on_connect = lambda c, u, f, rc, p: c.subscribe([("EventsTopic", 1)])
        self.c.connect(host, port)
        self.c.loop_start()

    def publish(self, topic, payload):
        self.c.publish(topic, json.dumps(payload), qos=1).wait_for_publish(WAIT)

    def expect(self, what, pred):
        deadline = time.monotonic() + WAIT
        while True:
            left = deadline - time.monotonic()
            check(left > 0, f"no {what} within {WAIT} s")
            try:
                _, payload = self.q.get(timeout=left)
            except queue.Empty:
                continue
            try:
                ev = json.loads(payload)
            except ValueError:
                continue
            if pred(ev):
                return ev


def expect_error(call, kind, contains):
    try:
        call()
    except Exception as e:  # noqa: BLE001 - the kind is checked by name below
        text = f"{type(e).__name__}: {e}"
        # A defined execution error is `UnknownElement: ...` (or a class of that name), a validation
        # error a `ValidationError`.
        check((kind in text.split(": ")[:2] or type(e).__name__ == kind) and contains in text, f"expected {kind} with {contains!r}, got {text}")
        print(f"ok: {text}")
        return e
    raise AssertionError(f"expected {kind}, the call succeeded")


def collect(subscription):
    """Every value `subscription` delivers, in a queue, from the first on. A callback added after
    `subscribe()` misses the values that came before it (the client's reader thread calls only the
    callbacks it has), and a property's first value comes at once; iterating reads the
    subscription's own queue, which has them all."""
    values = queue.Queue()

    def read():
        try:
            for value in subscription:
                values.put(value)
        except Exception:  # the stream cancelled or broken: the waits on `values` say so
            pass

    threading.Thread(target=read, daemon=True).start()
    return values


def wait_for(what, pred):
    deadline = time.monotonic() + WAIT
    while not pred():
        check(time.monotonic() < deadline, f"{what} not seen within {WAIT} s")
        time.sleep(0.05)


def first(host, sila_port, ca: Path, mqtt_port, sila_dir: Path, name, server_uuid):
    from sila2.client import SilaClient
    from sila2.client.utils import call_rpc_function
    from sila2.framework.pb2 import SiLAFramework_pb2 as fw

    events = Events(host, mqtt_port)
    # A plaintext client on the TLS port gets a clear error; the server keeps serving the next.
    expect_error(lambda: SilaClient(host, sila_port, insecure=True), "SilaConnectionError", "UNAVAILABLE")
    # Discovery: the announcement names the address and port and carries the certificate (ca0, ...).
    found = SilaClient.discover(server_uuid=server_uuid, timeout=WAIT)
    check((found.address, found.port) == (host, sila_port), f"discovered at {found.address}:{found.port}")
    check(found.SiLAService.ServerUUID.get() == server_uuid, "the discovered server's UUID")
    print(f"ok: discovered {server_uuid} at {found.address}:{found.port} over mDNS, TLS with its announced certificate")
    client = SilaClient(host, sila_port, root_certs=ca.read_bytes())
    svc = client.SiLAService
    check(svc.ServerType.get() == "IhexIsland", "server type")
    check(svc.ServerUUID.get() == server_uuid, "the UUID")
    features = svc.ImplementedFeatures.get()
    check(
        features
        == [
            "org.silastandard/core/SiLAService/v1",
            "de.ihex/bench/IslandControl/v1",
            "org.silastandard/core/LockController/v1",
            "de.ihex/bench/FirmwareUpdate/v1",
            "org.silastandard/core.commands/CancelController/v1",
        ],
        f"features {features}",
    )
    # Served verbatim: byte for byte the repository's definition.
    served = svc.GetFeatureDefinition("de.ihex/bench/IslandControl/v1").FeatureDefinition
    check(served == (sila_dir / "features" / "IslandControl.sila.xml").read_text(encoding="utf-8"), "served FDL")
    expect_error(
        lambda: svc.GetFeatureDefinition("de.ihex/bench/Nothing/v1"), "UnimplementedFeature", "does not implement"
    )
    print(f"ok: SiLAService: {svc.ServerName.get()!r} {server_uuid} {features}")

    # The client built IslandControl from the served definition.
    ic = client.IslandControl
    elements = {e.ElementId: e for e in ic.Elements.get()}
    check({"111", "112", "2"} <= set(elements), f"elements {sorted(elements)}")
    check(elements["111"].Role == "static" and elements["111"].Online, f"111: {elements['111']}")

    ic.SetLight(ElementId="111", Color="red", Brightness=50, BlinkPeriod=0, BlinkDuty=50)
    result = events.expect(
        "the SiLA command's command_result",
        lambda e: e.get("event") == "command_result" and str(e["payload"].get("request_id")).startswith("sila-"),
    )
    check(
        (result["payload"]["cmd"], result["payload"]["node"], result["payload"]["result"]) == ("led", "111", "ok"),
        f"command_result {result}",
    )
    light = {e.ElementId: e for e in ic.Elements.get()}["111"].Light
    check(light == "steady #ff0000 128", f"111's light after SetLight: {light!r}")
    print(f"ok: SetLight 111 red 50 % -> {light!r}, {json.dumps(result)}")

    expect_error(
        lambda: ic.SetLight(ElementId="5", Color="red", Brightness=50, BlinkPeriod=0, BlinkDuty=50),
        "UnknownElement",
        "unknown node 5",
    )
    # The client checks the constraints itself; the server must too, for clients that do not.
    expect_error(
        lambda: ic.SetLight(ElementId="111", Color="red", Brightness=150, BlinkPeriod=0, BlinkDuty=50),
        "ValidationError",
        "150",
    )
    raw = ic._pb2_module.SetLight_Parameters(
        ElementId=fw.String(value="111"),
        Color=fw.String(value="red"),
        Brightness=fw.Integer(value=150),
        BlinkPeriod=fw.Integer(value=0),
        BlinkDuty=fw.Integer(value=50),
    )
    e = expect_error(
        lambda: call_rpc_function(ic._grpc_stub.SetLight, raw, None, client, ic.SetLight._wrapped_command),
        "ValidationError",
        "Brightness must be 0 to 100 percent; got 150",
    )
    # The client resolves the identifier the server named to the parameter of its feature.
    named = str(e.parameter_fully_qualified_identifier.fully_qualified_identifier)
    check(named == "de.ihex/bench/IslandControl/v1/Command/SetLight/Parameter/Brightness", f"named {named}")
    raw.Color.value = "mauve"
    raw.Brightness.value = 50
    e = expect_error(
        lambda: call_rpc_function(ic._grpc_stub.SetLight, raw, None, client, ic.SetLight._wrapped_command),
        "ValidationError",
        "`color` must be",
    )
    named = str(e.parameter_fully_qualified_identifier.fully_qualified_identifier)
    check(named.endswith("/SetLight/Parameter/Color"), f"named {named}")

    # Dockings: one value now, then one per docking change done through the simulator.
    sub = ic.Dockings.subscribe()
    values = collect(sub)

    def next_dockings(what):
        try:
            return {(d.StaticElement, d.Port, d.MobileElement, d.MobilePort) for d in values.get(timeout=WAIT)}
        except queue.Empty:
            raise AssertionError(f"no Dockings value for {what} within {WAIT} s") from None

    now = next_dockings("the subscription")
    check(("111", 3, "2", 0) in now, f"dockings at start {now}")
    events.publish("ihex/sim", {"sim": "dock", "mobile": "3", "static": "112", "port": 2})
    docked = next_dockings("the dock")
    check(any(d[:3] == ("112", 2, "3") for d in docked - now), f"dockings after the dock {docked}")
    events.publish("ihex/sim", {"sim": "undock", "mobile": "3"})
    undocked = next_dockings("the undock")
    check(undocked == now, f"dockings after the undock {undocked}")
    sub.cancel()
    print(f"ok: Dockings {now} -> {docked} -> {undocked}")

    lock(client, events)

    svc.SetServerName(name)
    check(svc.ServerName.get() == name, "the new name")


def lock(client, events):
    """LockController: a lock is a lease on the whole island, honoured by SiLA and MQTT alike."""
    lc, ic = client.LockController, client.IslandControl
    check(lc.IsLocked.get() is False, "locked before LockServer")
    lc.LockServer(LockIdentifier="run-7", Timeout=60)
    check(lc.IsLocked.get() is True, "not locked after LockServer")
    mine = [lc.LockIdentifier("run-7")]

    def light(color, metadata=None):
        ic.SetLight(ElementId="111", Color=color, Brightness=50, BlinkPeriod=0, BlinkDuty=50, metadata=metadata)

    expect_error(lambda: light("blue"), "NotAllowed", "111 is leased by sila:")
    expect_error(lambda: light("blue", [lc.LockIdentifier("other")]), "InvalidLockIdentifier", "another lock")
    light("green", mine)
    got = {e.ElementId: e for e in ic.Elements.get()}["111"].Light
    check(got == "steady #00ff00 128", f"111's light after SetLight with the lock: {got!r}")
    # An MQTT client without the token is refused meanwhile, naming the holder.
    events.publish("CommandsTopic", {"cmd": "led", "node": "111", "color": "blue", "request_id": "mqtt-locked"})
    refused = events.expect(
        "the MQTT command's refusal",
        lambda e: e.get("payload", {}).get("request_id") == "mqtt-locked" if isinstance(e.get("payload"), dict) else False,
    )
    check(
        refused["event"] == "command_rejected" and "leased by sila:" in refused["payload"]["reason"],
        f"the MQTT command while locked: {refused}",
    )
    expect_error(lambda: lc.LockServer(LockIdentifier="run-8", Timeout=60), "ServerAlreadyLocked", "already locked")
    expect_error(lambda: lc.UnlockServer(LockIdentifier="other"), "InvalidLockIdentifier", "not the one")
    lc.UnlockServer(LockIdentifier="run-7")
    check(lc.IsLocked.get() is False, "locked after UnlockServer")
    expect_error(lambda: lc.UnlockServer(LockIdentifier="run-7"), "ServerNotLocked", "not locked")
    light("red")
    events.publish("CommandsTopic", {"cmd": "led", "node": "111", "color": "red", "request_id": "mqtt-free"})
    ok = events.expect(
        "the MQTT command's result",
        lambda e: e.get("payload", {}).get("request_id") == "mqtt-free" if isinstance(e.get("payload"), dict) else False,
    )
    check(ok["event"] == "command_result" and ok["payload"]["result"] == "ok", f"the MQTT command after unlock: {ok}")
    print(f"ok: LockController: locked, refused without the identifier ({refused['payload']['reason']!r}), accepted with it, unlocked")

    # The lock's Timeout counts from the last call with its identifier: calls keep it, silence ends it.
    lc.LockServer(LockIdentifier="run-9", Timeout=2)
    for _ in range(4):
        time.sleep(1.1)
        light("green", [lc.LockIdentifier("run-9")])
    check(lc.IsLocked.get() is True, "the lock ended although calls with its identifier kept coming")
    time.sleep(3)
    check(lc.IsLocked.get() is False, "the lock outlived its Timeout without calls")
    expect_error(lambda: lc.UnlockServer(LockIdentifier="run-9"), "ServerNotLocked", "already ended")
    print("ok: LockController: the Timeout counts from the last call with the lock identifier")


def firmware(host, sila_port, ca: Path, mqtt_port, small: Path, big: Path):
    """FirmwareUpdate over SiLA, its progress and result, its fw_report on MQTT, and CancelController."""
    from sila2.client import SilaClient
    from sila2.framework import CommandExecutionStatus

    events = Events(host, mqtt_port)
    client = SilaClient(host, sila_port, root_certs=ca.read_bytes())
    fu, cc = client.FirmwareUpdate, client.CancelController
    for image in (small, big):
        events.c.publish(f"ihex/fw/upload/{image.name}", image.read_bytes(), qos=1).wait_for_publish(WAIT)
        events.expect(
            f"the upload of {image.name}",
            lambda e, n=image.name: e.get("event") == "fw_upload" and e["payload"].get("name") == n,
        )
    expect_error(lambda: fu.UpdateFirmware(Image="nothing.img", Elements="111,112"), "ImageNotUsable", "nothing.img")
    expect_error(lambda: fu.UpdateFirmware(Image=small.name, Elements="111,5"), "UnknownElement", "unknown node 5")
    expect_error(
        lambda: cc.CancelCommand(CommandExecutionUUID=str(uuid.uuid4())), "InvalidCommandExecutionUUID", "not known"
    )

    # An update to its end: progress as intermediate responses, the outcomes as the result.
    run = fu.UpdateFirmware(Image=small.name, Elements="111,112")
    sub = run.subscribe_to_intermediate_responses()
    progress = collect(sub)
    try:
        first_step = progress.get(timeout=WAIT)
    except queue.Empty:
        raise AssertionError(f"no intermediate response within {WAIT} s") from None
    check(
        first_step.ElementId in ("111", "112") and 0 <= first_step.Percent <= 100,
        f"the first intermediate response {first_step}",
    )
    deadline = time.monotonic() + 120
    while not run.done:
        check(time.monotonic() < deadline, f"the update did not finish within 120 s: {run.status} {run.progress}")
        time.sleep(0.1)
    steps = [first_step]
    while not progress.empty():
        steps.append(progress.get())
    check(run.status == CommandExecutionStatus.finishedSuccessfully, f"status {run.status}")
    check(run.progress == 1.0, f"progress at the end {run.progress}")
    outcomes = {(o.ElementId, o.Outcome, o.Version, o.Reason) for o in run.get_responses().Outcomes}
    check(outcomes == {("111", "updated", "9.0.0", ""), ("112", "updated", "9.0.0", "")}, f"outcomes {outcomes}")
    report = events.expect("the update's fw_report", lambda e: e.get("event") == "fw_report")
    check(str(report["payload"]["request_id"]).startswith("sila-"), f"the fw_report of the SiLA update: {report}")
    check(
        {(n["node"], n["outcome"]) for n in report["payload"]["nodes"]} == {("111", "updated"), ("112", "updated")},
        f"fw_report {report}",
    )
    print(f"ok: UpdateFirmware {small.name}: {len(steps)} progress values ({steps[0]} ...), result {sorted(outcomes)}")

    # A second update, cancelled: the execution finishes with the error Cancelled, and so says fw_report.
    run = fu.UpdateFirmware(Image=big.name, Elements="111,112")
    expect_error(lambda: fu.UpdateFirmware(Image=small.name, Elements="111"), "UpdateRunning", "running")
    sub = run.subscribe_to_intermediate_responses()
    started = collect(sub)
    try:
        started.get(timeout=WAIT)
    except queue.Empty:
        raise AssertionError(f"no progress of the second update within {WAIT} s") from None
    cc.CancelCommand(CommandExecutionUUID=str(run.execution_uuid))
    cancel = events.expect(
        "fw_cancel's command_result",
        lambda e: e.get("event") == "command_result" and e["payload"].get("cmd") == "fw_cancel",
    )
    check(
        cancel["payload"]["result"] == "ok" and cancel["payload"].get("origin", {}).get("interface") == "sila",
        f"fw_cancel's answer {cancel}",
    )
    report = events.expect("the cancelled update's fw_report", lambda e: e.get("event") == "fw_report")
    reasons = {(n["node"], n["outcome"], n["reason"]) for n in report["payload"]["nodes"]}
    check(
        reasons == {("111", "failed", "cancelled by fw_cancel"), ("112", "failed", "cancelled by fw_cancel")},
        f"the cancelled update's fw_report {report}",
    )
    wait_for("the cancelled execution's end", lambda: run.done)
    check(run.status == CommandExecutionStatus.finishedWithError, f"status after cancel {run.status}")
    expect_error(run.get_responses, "Cancelled", "cancelled")
    expect_error(
        lambda: cc.CancelCommand(CommandExecutionUUID=str(run.execution_uuid)),
        "InvalidCommandExecutionUUID",
        "already finished",
    )
    cc.CancelAll()  # nothing runs: nothing to do
    print(f"ok: CancelController: {big.name} cancelled, fw_report {sorted(reasons)}")


def again(host, sila_port, ca: Path, server_uuid, name):
    from sila2.client import SilaClient

    client = SilaClient(host, sila_port, root_certs=ca.read_bytes())
    got = client.SiLAService.ServerUUID.get()
    check(got == server_uuid, f"UUID after a restart {got}, was {server_uuid}")
    check(client.SiLAService.ServerName.get() == name, "the name after a restart")
    print(f"ok: after a restart: {got} {name!r}")


def main(argv):
    mode = argv[1]
    if mode == "definitions":
        definitions(Path(argv[2]))
    elif mode == "first":
        first(argv[2], int(argv[3]), Path(argv[4]), int(argv[5]), Path(argv[6]), argv[7], argv[8])
    elif mode == "firmware":
        firmware(argv[2], int(argv[3]), Path(argv[4]), int(argv[5]), Path(argv[6]), Path(argv[7]))
    elif mode == "again":
        again(argv[2], int(argv[3]), Path(argv[4]), argv[5], argv[6])
    else:
        raise SystemExit(f"unknown mode {mode}")


def run(argv) -> int:
    """main's exit status: 0 when it returned, 1 (the reason on stderr) when it failed."""
    try:
        main(argv)
        return 0
    except SystemExit as e:
        if e.code in (None, 0):
            return 0
        print(e.code, file=sys.stderr)
        return 1
    except BaseException:
        traceback.print_exc()
        return 1


if __name__ == "__main__":
    status = run(sys.argv)
    sys.stdout.flush()
    sys.stderr.flush()
    # sila2's subscription threads are not daemons and may never end (a subscription whose value
    # did not come, after a failed check): the process ends here, whatever they do.
    os._exit(status)
