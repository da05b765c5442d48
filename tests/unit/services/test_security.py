"""services/security.py and the stack file's [security] table, machine endpoints (no Zenoh session)."""

import re
from pathlib import Path

import pytest

import schemas
from services import security
from services.stack import DEFAULT_STACK, StackError, load_stack

ROOT = Path(__file__).resolve().parents[3]

SERVICES = "\n".join(f'[services.{n}]\nmachine = "{m}"\nrate_hz = {r}\n' for n, m, r in (
    ("sim", "vehicle", 400.0), ("motors", "vehicle", 400.0), ("attitude", "vehicle", 200.0),
    ("position", "vehicle", 100.0), ("planner", "ground", 50.0), ("recorder", "ground", 10.0),
    ("mavlink", "ground", 50.0)))

SECURE = """
[security]
dir = "keys"
[machines.vehicle]
router = "tcp/127.0.0.1:7447"
runs_router = true
listen = ["tls/10.0.0.2:7448"]
[machines.ground]
router = "tcp/127.0.0.1:7447"
runs_router = true
connect = ["tls/10.0.0.2:7448"]
"""


def stack_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "stack.toml"
    path.write_text(text + SERVICES)
    return path


def test_publishes_matches_the_services_code():
    """PUBLISHES (what the access control lets a machine's services put) is what the code publishes."""
    for name, topics in security.PUBLISHES.items():
        code = (ROOT / "services" / f"{name}.py").read_text()
        used = {getattr(schemas, m).topic.replace("{service}", "*")
                for m in re.findall(r"(?:rt|io)\.publisher\(schemas\.(\w+)", code)}
        if name == "sim":   # its sensors, and the lockstep clocks it drives (services/lockstep.py)
            used |= {m.topic for m in schemas.SIM_TOPICS.values()}
            assert "io.publisher(msg)" in code
            assert "rt.publisher(schemas.CLOCK" in (ROOT / "services" / "lockstep.py").read_text()
            used.add(schemas.CLOCK.topic.replace("{service}", "*"))
        assert used == set(topics), name


def test_default_stack_listens_on_loopback_and_has_no_security():
    stack = load_stack(DEFAULT_STACK)
    assert stack.security is None
    for m in stack.machines.values():
        assert m.services_listen == ("tcp/127.0.0.1:0",) and not m.listen and not m.connect
        assert security.is_loopback(m.router)


def test_security_table_and_links(tmp_path):
    stack = load_stack(stack_file(tmp_path, SECURE))
    assert stack.security.dir == tmp_path / "keys"   # relative to the stack file
    assert stack.machines["vehicle"].listen == ("tls/10.0.0.2:7448",)
    assert stack.machines["ground"].connect == ("tls/10.0.0.2:7448",)


def test_a_secured_link_may_add_quic_for_the_streams(tmp_path):
    """QUIC runs TLS 1.3 with the same certificates; its datagrams carry best-effort streams
    (docs/security.md)."""
    quic = SECURE.replace('listen = ["tls/10.0.0.2:7448"]',
                          'listen = ["tls/10.0.0.2:7448?prio=0-6", "quic/10.0.0.2:7450?prio=0-6;rel=0"]', 1)
    stack = load_stack(stack_file(tmp_path, quic))
    assert stack.machines["vehicle"].listen[1] == "quic/10.0.0.2:7450?prio=0-6;rel=0"
    with pytest.raises(StackError, match="must be tls/HOST:PORT or quic/HOST:PORT"):
        load_stack(stack_file(tmp_path, quic.replace("quic/", "udp/")))


@pytest.mark.parametrize("change, message", [
    (('dir = "keys"', ''), "dir"),
    (('dir = "keys"', 'dir = "keys"\npassword = "x"'), "unknown key"),
    (('listen = ["tls/10.0.0.2:7448"]', 'listen = ["tcp/10.0.0.2:7448"]'), "must be tls"),
    (('connect = ["tls/10.0.0.2:7448"]', 'connect = ["tcp/10.0.0.2:7448"]'), "must be tls"),
    (('runs_router = true\nlisten', 'services_listen = ["tcp/0.0.0.0:0"]\nruns_router = true\nlisten'), "loopback only"),
    (('router = "tcp/127.0.0.1:7447"\nruns_router = true\nlisten', 'router = "tcp/10.0.0.2:7447"\nruns_router = true\nlisten'),
     "must be on loopback"),
    (('connect = ["tls/10.0.0.2:7448"]', 'connect = ["tls/10.0.0.2:7448"]\nlisten = ["tls/10.0.0.3:7448"]'), "not both"),
    (('listen = ["tls/10.0.0.2:7448"]', 'listen = ["10.0.0.2:7448"]'), "PROTOCOL/HOST:PORT"),
])
def test_bad_security_settings_are_refused_with_where(tmp_path, change, message):
    old, new = change
    assert old in SECURE
    with pytest.raises(StackError, match=message) as err:
        load_stack(stack_file(tmp_path, SECURE.replace(old, new, 1)))
    assert "stack.toml" in str(err.value)


def test_router_acl_lets_the_ground_publish_only_its_services_keys(tmp_path):
    stack = load_stack(stack_file(tmp_path, SECURE))
    acl = security.router_acl(stack, "vehicle")
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    ground = rules["publish-ground"]
    assert ground["messages"] == ["put"] and ground["flows"] == ["ingress"]
    keys = set(ground["key_exprs"])
    assert {"zp/0/planner/setpoint", "zp/0/planner/plan", "zp/0/planner/command", "zp/0/param/set",
            "zp/0/planner/health", "zp/0/@lockstep/sync/planner"} <= keys
    for forbidden in ("zp/0/att/command", "zp/0/motors/pwm", "zp/0/pos/setpoint", "zp/0/sim/imu", "zp/0/**"):
        assert forbidden not in keys
    # `**` does not match the handshake's verbatim @lockstep chunk: the machine's own sessions and
    # what every machine receives name it apart (without it a secured lockstep stack never ticks)
    for rule in ("everything", "declarations", "receive"):
        assert "zp/0/@lockstep/**" in rules[rule]["key_exprs"]
    policies = {p["id"]: p for p in acl["policies"]}
    assert policies["own-vehicle"]["rules"] == ["everything"]
    assert "everything" not in policies["from-ground"]["rules"]
    # the link check (deploy/router.py): the ground's ping in and its echo out, exact keys only
    assert rules["link-ground"]["key_exprs"] == ["zp/0/@link/ground/ping", "zp/0/@link/ground/echo"]
    assert "link-ground" in policies["from-ground"]["rules"]


def test_a_quic_link_is_checked_from_a_session_of_its_own(tmp_path):
    """A router connecting by QUIC (docs/reliability.md, "A secured split over an unreliable
    link"): its other-host endpoints go to the link's session, which listens only on loopback;
    the machine's router connects to that session alone. A TLS-only link stays as it was."""
    import json
    from deploy.router import checks_link, link_config, router_config
    links = '["tls/10.0.0.2:7448?prio=0-6", "quic/10.0.0.2:7450?prio=0-6;rel=0"]'
    quic = SECURE.replace('connect = ["tls/10.0.0.2:7448"]', f"connect = {links}", 1).replace(
        'listen = ["tls/10.0.0.2:7448"]', f"listen = {links}", 1)
    path = stack_file(tmp_path, quic)
    stack = load_stack(path)
    security.make_keys(tmp_path / "keys", stack)
    assert checks_link(stack, "ground") and not checks_link(stack, "vehicle")
    conf = json.loads(str(router_config([], str(path), "ground", "tcp/127.0.0.1:9999")[0]))
    assert conf["connect"]["endpoints"] == ["tcp/127.0.0.1:9999"]
    assert conf["listen"]["endpoints"] == [stack.machines["ground"].router]
    link = json.loads(str(link_config(stack, "ground", "tcp/127.0.0.1:9999")))
    assert link["listen"]["endpoints"] == ["tcp/127.0.0.1:9999"]
    assert link["connect"]["endpoints"] == json.loads(links)
    assert link["transport"]["auth"]["usrpwd"]["user"] == "ground"
    plain = load_stack(stack_file(tmp_path, SECURE))
    assert not checks_link(plain, "ground")


def test_a_link_of_several_endpoints_is_checked_one_of_one_is_not(tmp_path):
    """TLS at priorities 0-6 and TLS at 7-7 (the secured split's control and bulk links): the first
    declarations may go on either and arrive out of order; nothing crossed in 1 of 2 flights across
    lan (docs/reliability.md), so the connecting router checks it as a QUIC link, and the accepting
    router echoes. The same endpoints without [security] (an open split: it met the same across
    `bad`) too; a link of one endpoint is left as it was."""
    from deploy.router import checks_link, echoes_links
    links = '["tls/10.0.0.2:7448?prio=0-6", "tls/10.0.0.2:7449?prio=7-7"]'
    two = SECURE.replace('connect = ["tls/10.0.0.2:7448"]', f"connect = {links}", 1).replace(
        'listen = ["tls/10.0.0.2:7448"]', f"listen = {links}", 1)
    stack = load_stack(stack_file(tmp_path, two))
    assert checks_link(stack, "ground") and echoes_links(stack, "vehicle")
    assert not checks_link(stack, "vehicle") and not echoes_links(stack, "ground")
    one = load_stack(stack_file(tmp_path, SECURE))
    assert not checks_link(one, "ground") and not echoes_links(one, "vehicle")
    open_split = two.replace("[security]\ndir = \"keys\"\n", "").replace("tls/", "tcp/")
    assert "[security]" not in open_split
    plain = load_stack(stack_file(tmp_path, open_split))
    assert checks_link(plain, "ground") and echoes_links(plain, "vehicle")
    single = load_stack(stack_file(tmp_path, SECURE.replace("[security]\ndir = \"keys\"\n", "").replace("tls/", "tcp/")))
    assert not checks_link(single, "ground") and not echoes_links(single, "vehicle")


def test_a_router_watches_the_other_hosts_health_and_never_one_flying_the_vehicle():
    """deploy/router.py opens a lost link and its router again only after no echo and no health
    from the keys health_keys names: the other machines' services (the ground watches the
    vehicle's); a machine running the control services watches nothing (never opened again)."""
    from deploy.router import health_keys
    stack = load_stack(ROOT / "tests" / "integration" / "stacks" / "two-hosts-ground.toml")
    assert health_keys(stack, "ground") == [f"zp/0/{n}/health" for n in ("sim", "motors", "attitude", "position", "vision")]
    assert health_keys(stack, "vehicle") == []
    # the router machine beside the vehicle's services watches them too: they keep coming, it never re-links
    assert "zp/0/motors/health" in health_keys(stack, "vehicle-router")


def test_make_keys_writes_secret_files_private_and_never_overwrites(tmp_path):
    stack = load_stack(stack_file(tmp_path, SECURE))
    made = security.make_keys(tmp_path / "keys", stack)
    assert {p.name for p in made} >= {"ca.pem", "ca.key", "vehicle.pem", "vehicle.key", "ground.login", "ground.users"}
    for p in made:
        private = p.suffix in (".key", ".login", ".users")
        assert (p.stat().st_mode & 0o077 == 0) == private, p
    sec = stack.security
    assert sec.login("ground")[0] == "ground"
    # the vehicle's router accepts links: it knows every machine; the ground's only itself
    assert [line.split(":")[0] for line in sec.users_file("vehicle").read_text().split()] == ["vehicle", "ground"]
    assert [line.split(":")[0] for line in sec.users_file("ground").read_text().split()] == ["ground"]
    with pytest.raises(security.SecurityError, match="already exists"):
        security.make_keys(tmp_path / "keys", stack)


def test_missing_keys_say_how_to_make_them(tmp_path):
    stack = load_stack(stack_file(tmp_path, SECURE))
    with pytest.raises(security.SecurityError, match="zenpilot certs"):
        stack.security.login("vehicle")


def test_a_tool_acts_as_the_machine_whose_login_is_here(tmp_path):
    """On two hosts both routers are tcp/127.0.0.1:7447: `zenpilot status` on the ground uses the
    ground's login, the only one copied there."""
    stack = load_stack(stack_file(tmp_path, SECURE))
    assert security.machine_of(stack, "tcp/127.0.0.1:7447") == "vehicle"
    security.make_keys(tmp_path / "keys", stack)
    (tmp_path / "keys" / "vehicle.login").unlink()
    assert security.machine_of(stack, "tcp/127.0.0.1:7447") == "ground"
    with pytest.raises(security.SecurityError, match="no machine has router"):
        security.machine_of(stack, "tcp/127.0.0.1:1")
