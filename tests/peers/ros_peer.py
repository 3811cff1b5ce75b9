#!/usr/bin/env python3
"""labrig rclpy peer: a real ROS 2 (Kilted, rmw_fastrtps_cpp) process that the Rust
integration tests spawn to check interop.

Run it with the venv python made by scripts/setup.sh:

    source ~/.cache/labrig/env.sh
    "$LABRIG_ROS_PYTHON" tests/peers/ros_peer.py <subcommand> [options]

Required environment: FASTDDS_DEFAULT_PROFILES_FILE pointing at the loopback-only
profile (scripts/fastdds_loopback.xml); without it the script exits 3 so that no DDS
packet ever leaves loopback. ROS_DOMAIN_ID is honoured (set a distinct one per test).

Output protocol: stdout carries JSON objects only, one per line, flushed at once.
Native (Fast DDS) console output is redirected to stderr so it cannot corrupt the
stream. Non-finite floats are written as the strings "NaN", "Infinity", "-Infinity"
(and accepted as such on input) so that the output is strict JSON.

Subcommands (exit codes: 0 ok, 2 usage, 3 no loopback profile, 4 peer not found):
  cdr serialize          stdin: {"type": "sensor_msgs/msg/JointState", "value": {...}}
                         stdout: {"hex": "..."} | {"error": "..."}
                         hex = rclpy.serialization.serialize_message() exactly as
                         returned, encapsulation header included. rmw_serialize never
                         writes the alignment padding and sizes its buffer by an
                         estimate, so those bytes are whatever malloc handed out: run
                         this under glibc's malloc perturb tunable (see
                         tests/tests/cdr_rclpy.rs) to tell them from the data.
  cdr deserialize        stdin: {"type": ..., "hex": ...}
                         stdout: {"value": {...}} | {"error": "..."}
  listen-joint-states --topic T --count N --timeout S
                         one line per message; recv_mono_ns = time.monotonic_ns() when
                         rclpy's callback got it (for arrival rates), recv_ns = wall clock
  listen --topic T --type TYPE --count N --timeout S    (same, any type: standard ones, and
                         labrig_msgs' generated from ros2/labrig_msgs when LABRIG_ROS_MSGS is set)
  drive-arm --target q1,..,q7 --seconds S     labrig_msgs/msg/ArmCommand in joint position mode
                         to /arm/command at 20 Hz, labrig_msgs/msg/RobotState read from /arm/state
  talk-pose --topic T --count N --rate HZ
  talk-string-forever --topic T --rate HZ --max-seconds S
  serve-addtwoints --service S --max-seconds X     (std_srvs/srv/SetBool server)
  call-setbool --service S --data true|false --timeout S
"""

import argparse
import importlib
import json
import math
import os
import sys
import time

# --------------------------------------------------------------------------- output
# Keep a private handle on the real stdout for our JSON lines, then point fd 1 at
# stderr so that anything native code prints (Fast DDS' default log consumer writes
# to std::cout) cannot interleave with the protocol.
_OUT = os.fdopen(os.dup(1), "w", buffering=1, encoding="utf-8")
os.dup2(2, 1)
sys.stdout = sys.stderr


def _json_safe(v):
    if isinstance(v, float) and not math.isfinite(v):
        return "NaN" if math.isnan(v) else ("Infinity" if v > 0 else "-Infinity")
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_json_safe(x) for x in v]
    return v


def emit(obj):
    _OUT.write(json.dumps(_json_safe(obj), allow_nan=False, separators=(",", ":")) + "\n")
    _OUT.flush()


def die(code, msg):
    print(f"ros_peer: {msg}", file=sys.stderr, flush=True)
    sys.exit(code)


def require_loopback_profile():
    path = os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE", "")
    if not path:
        die(3, "FASTDDS_DEFAULT_PROFILES_FILE is unset; refusing to start DDS without the "
               "loopback-only profile (source ~/.cache/labrig/env.sh after scripts/setup.sh)")
    if not os.path.isfile(path):
        die(3, f"FASTDDS_DEFAULT_PROFILES_FILE={path} does not exist")
    # Fast DDS only logs XML errors and then runs with its defaults (multicast, every
    # interface), so check the profile's shape here and the sockets after start-up.
    problem = _profile_problem(path)
    if problem:
        die(3, f"FASTDDS_DEFAULT_PROFILES_FILE={path} is not a loopback-only profile: {problem}")
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    # The XML profile alone must decide where DDS goes. rmw_fastrtps edits the
    # participant after loading it, depending on ROS_AUTOMATIC_DISCOVERY_RANGE:
    #   unset/SUBNET -> adds 239.255.0.1:<7400+250*domain> to the initial peers
    #                   (SPDP multicast, though on lo only with this profile);
    #   LOCALHOST    -> adds an any-address metatraffic locator: the participant
    #                   advertises and binds the eth0 address too;
    #   SYSTEM_DEFAULT -> leaves the profile untouched: unicast 127.0.0.1 only.
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "SYSTEM_DEFAULT") != "SYSTEM_DEFAULT":
        print(f"ros_peer: overriding ROS_AUTOMATIC_DISCOVERY_RANGE="
              f"{os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']!r} with SYSTEM_DEFAULT",
              file=sys.stderr)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
    for var in ("ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY"):
        if var in os.environ:
            print(f"ros_peer: ignoring {var}={os.environ[var]!r}, the XML profile rules",
                  file=sys.stderr)
            del os.environ[var]


def _is_loopback(addr):
    return addr.startswith("127.") or addr in ("::1", "lo")


def _profile_problem(path):
    """None when `path` is a Fast DDS profile whose default participant uses only
    transports whitelisted to loopback, else a description of what is wrong."""
    import xml.etree.ElementTree as ET
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        return f"unreadable XML ({e})"
    local = lambda el: el.tag.rsplit("}", 1)[-1]  # noqa: E731 - drop the namespace
    find = lambda el, name: [x for x in el.iter() if local(x) == name]  # noqa: E731
    defaults = [p for p in find(root, "participant")
                if p.get("is_default_profile", "").lower() == "true"]
    if len(defaults) != 1:
        return "needs exactly one <participant is_default_profile=\"true\">"
    part = defaults[0]
    builtin = find(part, "useBuiltinTransports")
    if not builtin or builtin[0].text.strip().lower() != "false":
        return "the default participant must set <useBuiltinTransports>false"
    ids = [t.text.strip() for u in find(part, "userTransports") for t in find(u, "transport_id")]
    if not ids:
        return "the default participant has no <userTransports>"
    descs = {(find(d, "transport_id") or [None])[0].text.strip(): d
             for d in find(root, "transport_descriptor") if find(d, "transport_id")}
    for tid in ids:
        d = descs.get(tid)
        if d is None:
            return f"transport {tid!r} is not defined"
        allowed = [a.text.strip() for w in find(d, "interfaceWhiteList") for a in w
                   if a.text] + [i.get("name", "") for a in find(d, "allowlist") for i in a]
        if not allowed or not all(_is_loopback(a) for a in allowed):
            return f"transport {tid!r} is not whitelisted to loopback only ({allowed})"
    return None


def check_sockets():
    """Exit 3 if this process holds a UDP/TCP socket bound to a non-loopback address
    (i.e. the profile did not take effect)."""
    import ipaddress
    import struct
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    bad = []
    for table in ("udp", "udp6", "tcp", "tcp6"):
        try:
            lines = open(f"/proc/net/{table}").read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if f[9] not in inodes:
                continue
            hexaddr, port = f[1].split(":")
            # the kernel prints each 32-bit word of the address as a host-order int
            raw = b"".join(struct.pack("=I", int(hexaddr[i:i + 8], 16))
                           for i in range(0, len(hexaddr), 8))
            addr = ipaddress.ip_address(raw)
            if addr.version == 6:
                addr = addr.ipv4_mapped or addr
            if not addr.is_loopback:
                bad.append(f"{table} {addr}:{int(port, 16)}")
    if bad:
        die(3, "DDS opened non-loopback sockets, the loopback profile did not take effect: "
               + ", ".join(sorted(bad)))


# --------------------------------------------------------------------------- message <-> JSON
def resolve_type(name, kind="msg"):
    """'sensor_msgs/msg/JointState' or 'sensor_msgs/JointState' -> class."""
    parts = [p for p in name.replace("::", "/").replace(".", "/").split("/") if p]
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3:
        raise ValueError(f"bad type name {name!r}")
    mod = importlib.import_module(f"{parts[0]}.{parts[1]}")
    try:
        return getattr(mod, parts[2])
    except AttributeError:
        raise ValueError(f"unknown type {name!r}") from None


_FLOAT_TYPES = {"float", "double", "long double"}
_INT_RANGES = {f"{s}int{n}": ((0, 2**n - 1) if s else (-2**(n - 1), 2**(n - 1) - 1))
               for s in ("", "u") for n in (8, 16, 32, 64)}
_INT_RANGES.update({"char": (0, 255), "octet": (0, 255)})


def _slot_class(slot_type):
    # rosidl_parser.definition.NamespacedType
    return getattr(importlib.import_module(".".join(slot_type.namespaces)), slot_type.name)


def _from_json_scalar(slot_type, v):
    from rosidl_parser import definition as d
    if isinstance(slot_type, d.NamespacedType):
        return dict_to_msg(_slot_class(slot_type), v)
    if isinstance(slot_type, d.AbstractGenericString):
        if not isinstance(v, str):
            raise TypeError(f"expected a string, got {v!r}")
        return v
    if isinstance(slot_type, d.BasicType):
        t = slot_type.typename
        if t in _FLOAT_TYPES:
            if isinstance(v, str):
                return float({"NaN": "nan", "Infinity": "inf", "-Infinity": "-inf"}.get(v, v))
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise TypeError(f"expected a number, got {v!r}")
            return float(v)
        if t == "boolean":
            if not isinstance(v, bool):
                raise TypeError(f"expected a bool, got {v!r}")
            return v
        if t == "byte":
            # rclpy represents `byte` as a length-1 bytes object
            return bytes([v]) if isinstance(v, int) else bytes(v)
        if t in _INT_RANGES:
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(f"expected an integer, got {v!r}")
            lo, hi = _INT_RANGES[t]
            if not lo <= v <= hi:
                raise ValueError(f"{v} out of range for {t}")
            return v
    raise TypeError(f"unsupported slot type {slot_type!r}")


def dict_to_msg(cls, value):
    from rosidl_parser import definition as d
    if not isinstance(value, dict):
        raise TypeError(f"{cls.__name__}: expected an object, got {value!r}")
    msg = cls()
    fields = list(msg.get_fields_and_field_types().keys())
    unknown = set(value) - set(fields)
    if unknown:
        raise KeyError(f"{cls.__name__} has no field(s) {sorted(unknown)}")
    for field, slot in zip(fields, cls.SLOT_TYPES):
        if field not in value:
            continue
        v = value[field]
        if isinstance(slot, d.AbstractNestedType):
            if not isinstance(v, list):
                raise TypeError(f"{cls.__name__}.{field}: expected a list, got {v!r}")
            v = [_from_json_scalar(slot.value_type, x) for x in v]
        else:
            v = _from_json_scalar(slot, v)
        try:
            setattr(msg, field, v)
        except (AssertionError, TypeError, ValueError) as e:
            raise TypeError(f"{cls.__name__}.{field}: invalid value {value[field]!r} ({e})") \
                from None
    return msg


def _to_json(v):
    if hasattr(v, "get_fields_and_field_types"):
        return msg_to_dict(v)
    if isinstance(v, (bytes, bytearray)):
        return list(v) if len(v) != 1 else v[0]
    if isinstance(v, (list, tuple)):
        return [_to_json(x) for x in v]
    if hasattr(v, "tolist"):  # numpy arrays / scalars, array.array
        return _to_json(v.tolist())
    if isinstance(v, (bool, int, float, str)) or v is None:
        return v
    raise TypeError(f"cannot convert {type(v).__name__} to JSON")


def msg_to_dict(msg):
    out = {}
    for field in msg.get_fields_and_field_types():
        v = getattr(msg, field)
        if isinstance(v, (bytes, bytearray)) and len(v) == 1:
            # a single `byte` field; byte[] sequences are lists of length-1 bytes
            out[field] = v[0]
        elif isinstance(v, list) and v and isinstance(v[0], (bytes, bytearray)):
            out[field] = [b[0] for b in v]
        else:
            out[field] = _to_json(v)
    return out


def cmd_cdr(args):
    from rclpy.serialization import deserialize_message, serialize_message
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            req = json.loads(line)
            cls = resolve_type(req["type"])
            if args.direction == "serialize":
                msg = dict_to_msg(cls, req.get("value", {}))
                emit({"hex": serialize_message(msg).hex()})
            else:
                msg = deserialize_message(bytes.fromhex(req["hex"]), cls)
                emit({"value": msg_to_dict(msg)})
        except Exception as e:  # noqa: BLE001 - reported to the caller
            emit({"error": f"{type(e).__name__}: {e}"})
    return 0


# --------------------------------------------------------------------------- DDS helpers
def make_node(kind):
    import rclpy
    from rclpy.node import Node
    rclpy.init()
    node = Node(f"labrig_peer_{kind}_{os.getpid()}")
    check_sockets()
    return rclpy, node


def shutdown(rclpy, node):
    try:
        node.destroy_node()
    finally:
        if rclpy.ok():
            rclpy.shutdown()


def qos(depth):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                      depth=depth, durability=DurabilityPolicy.VOLATILE)


def wait_for_subscribers(pub, timeout_s):
    deadline = time.monotonic() + timeout_s
    while pub.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _listen(topic, cls, to_json, count, timeout):
    """Subscribe, emit {"ready"}, {"matched": n} once a writer is matched, then one JSON line
    per message until count or timeout."""
    rclpy, node = make_node("listen")
    received = 0

    def on_msg(m):
        nonlocal received
        # Taken first thing in the callback: when this rclpy node got the message. Monotonic,
        # so that gaps between arrivals are real durations (tests assert receive rates on it).
        recv_mono_ns = time.monotonic_ns()
        recv_ns = time.time_ns()
        received += 1
        emit({**to_json(m), "recv_ns": recv_ns, "recv_mono_ns": recv_mono_ns})

    sub = node.create_subscription(cls, topic, on_msg, qos(1000))
    emit({"ready": True})
    deadline = time.monotonic() + timeout
    matched = False
    try:
        while received < count and time.monotonic() < deadline:
            # Said once this reader has matched a writer (both sides of discovery done).
            if not matched and sub.get_publisher_count() > 0:
                matched = True
                emit({"matched": sub.get_publisher_count(), "type_hashes": _type_hashes(node, topic)})
            rclpy.spin_once(node, timeout_sec=min(0.05, max(0.0, deadline - time.monotonic())))
    finally:
        emit({"done": True, "received": received})
        shutdown(rclpy, node)
    return 0


def _type_hashes(node, topic):
    """The type hash of each endpoint of `topic` as rclpy sees it (its own subscription's
    from the generated type support; a peer's from discovery, invalid when it announced none)."""
    out = []
    for kind, infos in (("publisher", node.get_publishers_info_by_topic(topic)),
                        ("subscription", node.get_subscriptions_info_by_topic(topic))):
        for i in infos:
            out.append({"kind": kind, "node": i.node_name, "type": i.topic_type,
                        "type_hash": str(i.topic_type_hash)})
    return out


def cmd_drive_arm(args):
    """A planner of one's own on the rig: labrig_msgs/msg/ArmCommand (generated type) in joint
    position mode toward --target at --rate, reading labrig_msgs/msg/RobotState on --state;
    one line per state read, then a summary."""
    from labrig_msgs.msg import ArmCommand, RobotState
    rclpy, node = make_node("drive_arm")
    target = [float(x) for x in args.target.split(",")]
    states = []
    node.create_subscription(RobotState, args.state, lambda m: states.append(m), qos(100))
    pub = node.create_publisher(ArmCommand, args.command, qos(10))
    if not wait_for_subscribers(pub, args.wait_subscriber):
        shutdown(rclpy, node)
        die(4, f"no subscriber on {args.command} within {args.wait_subscriber} s")
    emit({"ready": True, "type_hashes": _type_hashes(node, args.command)})
    seq, first = 0, None
    deadline = time.monotonic() + args.seconds
    next_send = time.monotonic()
    try:
        while time.monotonic() < deadline:
            if time.monotonic() >= next_send:
                cmd = ArmCommand()
                cmd.version = 1
                cmd.header.stamp = node.get_clock().now().to_msg()
                cmd.header.frame_id = "base"
                cmd.mode = ArmCommand.MODE_JOINT_POSITION
                cmd.joint_position = target
                seq += 1
                cmd.seq = seq
                pub.publish(cmd)
                next_send += 1.0 / args.rate
            rclpy.spin_once(node, timeout_sec=0.005)
            while states:
                m = states.pop(0)
                q = [float(x) for x in m.joint_positions]
                first = first or q
                emit({"state": {"version": m.version, "mode": m.mode, "joint_positions": q,
                                "fault": m.fault, "sec": m.header.stamp.sec}})
    finally:
        emit({"done": True, "commands": seq})
        shutdown(rclpy, node)
    return 0


def cmd_listen_joint_states(args):
    from sensor_msgs.msg import JointState

    def to_json(m):
        return {"name": list(m.name), "position": list(m.position),
                "velocity": list(m.velocity), "effort": list(m.effort),
                "stamp": {"sec": m.header.stamp.sec, "nanosec": m.header.stamp.nanosec},
                "frame_id": m.header.frame_id}

    return _listen(args.topic, JointState, to_json, args.count, args.timeout)


def cmd_listen(args):
    """Any message type: one JSON line per message (its fields), then a summary."""
    return _listen(args.topic, resolve_type(args.type),
                   lambda m: {"topic": args.topic, "msg": msg_to_dict(m)}, args.count, args.timeout)


def _flush_reliable(pub, timeout_s=5.0):
    # let reliable writers get their samples acknowledged before the process exits
    from rclpy.duration import Duration
    try:
        pub.wait_for_all_acked(Duration(seconds=timeout_s))
    except Exception as e:  # noqa: BLE001
        print(f"ros_peer: wait_for_all_acked: {e}", file=sys.stderr)


def cmd_talk_pose(args):
    from geometry_msgs.msg import PoseStamped
    rclpy, node = make_node("talk_pose")
    pub = node.create_publisher(PoseStamped, args.topic, qos(100))
    emit({"ready": True})
    try:
        if not wait_for_subscribers(pub, args.wait_subscriber):
            emit({"error": f"no subscriber on {args.topic} after {args.wait_subscriber} s"})
            return 4
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        start = time.monotonic()
        for i in range(args.count):
            m = PoseStamped()
            m.header.frame_id = "base"
            m.header.stamp.sec = i
            m.header.stamp.nanosec = i * 1000
            m.pose.position.x = float(i)
            m.pose.position.y = float(2 * i)
            m.pose.position.z = float(3 * i)
            m.pose.orientation.w = 1.0
            pub.publish(m)
            if i + 1 < args.count and period:
                delay = start + (i + 1) * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        _flush_reliable(pub)
        emit({"published": args.count})
    finally:
        shutdown(rclpy, node)
    return 0


def cmd_talk_string_forever(args):
    from std_msgs.msg import String
    rclpy, node = make_node("talk_string")
    pub = node.create_publisher(String, args.topic, qos(10))
    emit({"ready": True})
    period = 1.0 / args.rate if args.rate > 0 else 0.1
    start = time.monotonic()
    i = 0
    try:
        while time.monotonic() - start < args.max_seconds:
            pub.publish(String(data=f"hello {i}"))
            i += 1
            delay = start + i * period - time.monotonic()
            if delay > 0:
                time.sleep(min(delay, max(0.0, start + args.max_seconds - time.monotonic())))
        emit({"published": i})
    finally:
        shutdown(rclpy, node)
    return 0


def cmd_serve_setbool(args):
    from std_srvs.srv import SetBool
    rclpy, node = make_node("serve")
    answered = 0

    def handle(req, resp):
        nonlocal answered
        resp.success = not req.data
        resp.message = "got true" if req.data else "got false"
        answered += 1
        emit({"request": {"data": req.data}, "answered": answered})
        return resp

    node.create_service(SetBool, args.service, handle)
    emit({"ready": True})
    deadline = time.monotonic() + args.max_seconds
    try:
        while answered < args.max_requests and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=min(0.05, max(0.0, deadline - time.monotonic())))
        # the last response is sent reliably; give it a moment on the wire (and for
        # retransmission) before the writer disappears
        linger = time.monotonic() + 0.5
        while time.monotonic() < linger:
            rclpy.spin_once(node, timeout_sec=0.05)
        emit({"done": True, "answered": answered})
    finally:
        shutdown(rclpy, node)
    return 0


def cmd_call_setbool(args):
    from std_srvs.srv import SetBool
    rclpy, node = make_node("call")
    try:
        cli = node.create_client(SetBool, args.service)
        deadline = time.monotonic() + args.timeout
        if not cli.wait_for_service(timeout_sec=args.timeout):
            emit({"error": f"service {args.service} not available after {args.timeout} s"})
            return 4
        fut = cli.call_async(SetBool.Request(data=args.data))
        rclpy.spin_until_future_complete(node, fut,
                                         timeout_sec=max(0.1, deadline - time.monotonic()))
        if not fut.done() or fut.result() is None:
            emit({"error": f"no response from {args.service} within {args.timeout} s"})
            return 4
        r = fut.result()
        emit({"success": r.success, "message": r.message})
    finally:
        shutdown(rclpy, node)
    return 0


# --------------------------------------------------------------------------- CLI
def _bool(s):
    v = s.strip().lower()
    if v in ("true", "1", "yes"):
        return True
    if v in ("false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError(f"expected true|false, got {s!r}")


def main(argv=None):
    p = argparse.ArgumentParser(prog="ros_peer.py", description=__doc__.split("\n\n")[0].replace("\n", " "))
    sub = p.add_subparsers(dest="cmd", required=True)

    c = sub.add_parser("cdr", help="serialize/deserialize JSON <-> CDR (stdin lines)")
    c.add_argument("direction", choices=["serialize", "deserialize"])
    c.set_defaults(fn=cmd_cdr)

    c = sub.add_parser("listen-joint-states")
    c.add_argument("--topic", required=True)
    c.add_argument("--count", type=int, required=True)
    c.add_argument("--timeout", type=float, required=True)
    c.set_defaults(fn=cmd_listen_joint_states)

    c = sub.add_parser("listen", help="subscribe to any topic of a standard type, print messages as JSON")
    c.add_argument("--topic", required=True)
    c.add_argument("--type", required=True, help="e.g. sensor_msgs/msg/CameraInfo")
    c.add_argument("--count", type=int, required=True)
    c.add_argument("--timeout", type=float, required=True)
    c.set_defaults(fn=cmd_listen)

    c = sub.add_parser("drive-arm", help="labrig_msgs ArmCommand toward a joint target, reading RobotState")
    c.add_argument("--target", required=True, help="seven joint positions, comma-separated (rad)")
    c.add_argument("--command", default="/arm/command")
    c.add_argument("--state", default="/arm/state")
    c.add_argument("--rate", type=float, default=20.0)
    c.add_argument("--seconds", type=float, required=True)
    c.add_argument("--wait-subscriber", type=float, default=30.0)
    c.set_defaults(fn=cmd_drive_arm)

    c = sub.add_parser("talk-pose")
    c.add_argument("--topic", required=True)
    c.add_argument("--count", type=int, required=True)
    c.add_argument("--rate", type=float, required=True)
    c.add_argument("--wait-subscriber", type=float, default=20.0,
                   help="seconds to wait for a subscriber before exiting 4 (default 20)")
    c.set_defaults(fn=cmd_talk_pose)

    c = sub.add_parser("talk-string-forever")
    c.add_argument("--topic", required=True)
    c.add_argument("--rate", type=float, required=True)
    c.add_argument("--max-seconds", type=float, required=True)
    c.set_defaults(fn=cmd_talk_string_forever)

    c = sub.add_parser("serve-addtwoints", aliases=["serve-setbool"],
                       help="std_srvs/srv/SetBool server: success = not data")
    c.add_argument("--service", required=True)
    c.add_argument("--max-seconds", type=float, required=True)
    c.add_argument("--max-requests", type=int, default=3)
    c.set_defaults(fn=cmd_serve_setbool)

    c = sub.add_parser("call-setbool")
    c.add_argument("--service", required=True)
    c.add_argument("--data", type=_bool, required=True)
    c.add_argument("--timeout", type=float, required=True)
    c.set_defaults(fn=cmd_call_setbool)

    args = p.parse_args(argv)
    require_loopback_profile()
    try:
        return args.fn(args)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
