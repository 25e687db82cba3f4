"""TLS links and secure-by-default routers (docs/security.md).

Real processes on free loopback ports: a router with login, the role rules and mutual TLS
(``tls/127.0.0.1:<port>``) lets nothing through from a client without a certificate, with a
certificate from another CA, or with a certificate but no password; a correctly configured
actor/critic/plant run works over ``tls/``; the README's "add a host" commands, run as written
(with the host names, directories and port substituted), connect a new host. A router on a
non-loopback endpoint refuses to start without login and TLS unless explicitly opted out.
"""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from common.config.settings import Settings, TransportSettings
from common.net.certs import write_tls_material
from common.net.security import ROLES, SecurityError, check_network_exposure, is_loopback, write_credentials
from common.net.transport import zenoh_config
from tests.harness import ROOT, Proc, free_port, wait_until

ROBOT = "tls"


# -- units ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("endpoint", "loopback"),
    [
        ("tcp/127.0.0.1:7447", True),
        ("tls/127.0.0.2:1", True),
        ("tcp/[::1]:7447", True),
        ("tcp/localhost:7447", True),
        ("tls/127.0.0.1:7447#iface=lo", True),
        ("tcp/0.0.0.0:7447", False),
        ("tls/[::]:7447", False),
        ("tcp/router:7447", False),
        ("tcp/192.168.1.20:7447", False),
        ("udp/10.0.0.1:7447", False),
    ],
)
def test_loopback_endpoints(endpoint: str, loopback: bool) -> None:
    assert is_loopback(endpoint) is loopback


def _transport(**values: Any) -> TransportSettings:
    return Settings.load(transport=values).transport


def test_a_network_router_needs_login_and_tls(tmp_path: Path) -> None:
    files = write_tls_material(tmp_path / "tls", ROLES)
    tls = {"tls_ca": str(files.ca), "tls_cert": str(files.cert("router")), "tls_key": str(files.key("router"))}
    for values, listen in [
        ({}, ["tcp/0.0.0.0:7447"]),  # open: finding 9
        ({"secure": True, "users_file": "x"}, ["tcp/0.0.0.0:7447"]),  # login but clear text
        ({**tls}, ["tls/0.0.0.0:7447"]),  # TLS but no login
        ({"secure": True}, ["tls/0.0.0.0:7447"]),  # no certificates
        ({"secure": True, **tls}, ["tcp/127.0.0.1:7447", "tcp/10.1.2.3:7447"]),
    ]:
        with pytest.raises(SecurityError, match="refusing to run a router"):
            check_network_exposure(_transport(**values), listen)
    check_network_exposure(_transport(), ["tcp/127.0.0.1:7447"])  # loopback: as before
    check_network_exposure(_transport(secure=True, **tls), ["tls/0.0.0.0:7447"])
    check_network_exposure(_transport(allow_insecure_network=True), ["tcp/0.0.0.0:7447"])  # the opt-out


@pytest.mark.integration
def test_certs_are_private_and_named_by_role(tmp_path: Path) -> None:
    out = tmp_path / "secrets"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "certs",
            "--out",
            str(out),
            "--hosts",
            "router",
            "192.168.1.20",
            "--passwords",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(
        [
            "ca.pem",
            "ca.key",
            "router.pem",
            "router.key",
            "users.txt",
            *(f"{r}.{ext}" for r in ROLES for ext in ("pem", "key", "password")),
        ]
    )
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in out.iterdir())
    router = x509.load_pem_x509_certificate((out / "router.pem").read_bytes())
    sans = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert set(sans.get_values_for_type(x509.DNSName)) == {"localhost", "router"}
    assert {str(a) for a in sans.get_values_for_type(x509.IPAddress)} == {"127.0.0.1", "::1", "192.168.1.20"}
    ca = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes())
    for role in ROLES:
        cert = x509.load_pem_x509_certificate((out / f"{role}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role
        cert.verify_directly_issued_by(ca)
    again = subprocess.run(
        [sys.executable, "-m", "tools.cli", "certs", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert again.returncode == 2 and "already holds a CA" in again.stderr  # never overwritten
    kept = subprocess.run(
        [sys.executable, "-m", "tools.cli", "certs", "--out", str(out), "--if-missing"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert kept.returncode == 0 and "kept" in kept.stdout


@pytest.mark.integration
def test_router_off_loopback_refuses_to_start() -> None:
    """``srl router`` on a network address (TEST-NET-1: nothing is ever bound) without login and
    TLS exits 2 with one clear line, before Zenoh tries to listen."""
    done = subprocess.run(
        [sys.executable, "-m", "tools.cli", "router", "--router", "tcp/192.0.2.1:7447"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "refusing to run a router on tcp/192.0.2.1:7447" in done.stderr
    assert "allow_insecure_network" in done.stderr and "Traceback" not in done.stderr


# -- processes -------------------------------------------------------------------------------------
def _role_env(secrets: Path, tls: Path, role: str) -> dict[str, str]:
    return {
        "SRL_TRANSPORT__SECURE": "true",
        "SRL_TRANSPORT__USER": role,
        "SRL_TRANSPORT__PASSWORD_FILE": str(secrets / f"{role}.password"),
        "SRL_TRANSPORT__TLS_CA": str(tls / "ca.pem"),
        "SRL_TRANSPORT__TLS_CERT": str(tls / f"{role}.pem"),
        "SRL_TRANSPORT__TLS_KEY": str(tls / f"{role}.key"),
        "SRL_CRITIC__CHECKPOINT": "",
    }


@contextmanager
def tls_router(tmp_path: Path) -> Iterator[tuple[str, Path, Path, Proc]]:
    secrets = tmp_path / "secrets"
    write_credentials(secrets)
    write_tls_material(secrets / "tls", ROLES)
    tls = secrets / "tls"
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = Proc(
        "router",
        ["router", "--router", endpoint, "--robot", ROBOT],
        env={
            "SRL_TRANSPORT__SECURE": "true",
            "SRL_TRANSPORT__USERS_FILE": str(secrets / "users.txt"),
            "SRL_TRANSPORT__TLS_CA": str(tls / "ca.pem"),
            "SRL_TRANSPORT__TLS_CERT": str(tls / "router.pem"),
            "SRL_TRANSPORT__TLS_KEY": str(tls / "router.key"),
        },
    )
    try:
        yield endpoint, secrets, tls, router
    finally:
        router.stop()


def _session(endpoint: str, **values: Any) -> zenoh.Session:
    return zenoh.open(zenoh_config(_transport(router=endpoint, robot=ROBOT, **values)))


def _login(endpoint: str, secrets: Path, tls: Path, role: str, **override: Any) -> dict[str, Any]:
    values: dict[str, Any] = {
        "secure": True,
        "user": role,
        "password_file": str(secrets / f"{role}.password"),
        "tls_ca": str(tls / "ca.pem"),
        "tls_cert": str(tls / f"{role}.pem"),
        "tls_key": str(tls / f"{role}.key"),
    }
    values.update(override)
    return values


def _open_or_none(endpoint: str, values: dict[str, Any]) -> zenoh.Session | None:
    try:
        return _session(endpoint, **values)
    except zenoh.ZError:
        return None


@pytest.mark.integration
@pytest.mark.slow
def test_tls_router_lets_nothing_through_without_certificate_ca_or_password(tmp_path: Path) -> None:
    other = write_tls_material(tmp_path / "other-ca", ROLES)  # a stranger's own CA, same role names
    with tls_router(tmp_path) as (endpoint, secrets, tls, router):

        def reachable() -> bool:
            session = _open_or_none(endpoint, _login(endpoint, secrets, tls, "monitor"))
            if session is not None:
                session.close()
            return session is not None

        wait_until(reachable, 30, "the TLS router")
        monitor = _session(endpoint, **_login(endpoint, secrets, tls, "monitor"))
        plant = _session(endpoint, **_login(endpoint, secrets, tls, "plant"))
        states: list[bytes] = []
        actions: list[bytes] = []
        monitor.declare_subscriber(f"srl/{ROBOT}/state", lambda s: states.append(bytes(s.payload.to_bytes())))
        plant.declare_subscriber(f"srl/{ROBOT}/action", lambda s: actions.append(bytes(s.payload.to_bytes())))
        attackers = {
            "no certificate": _login(endpoint, secrets, tls, "actor", tls_cert="", tls_key="", tls_mtls=False),
            "certificate of another CA": _login(
                endpoint, secrets, tls, "actor", tls_cert=str(other.cert("actor")), tls_key=str(other.key("actor"))
            ),
            "trusts another CA": _login(endpoint, secrets, tls, "actor", tls_ca=str(other.ca)),
            "certificate, no password": {**_login(endpoint, secrets, tls, "actor"), "secure": False},
            "certificate, wrong password": _login(
                endpoint, secrets, tls, "actor", password_file="", password="not-the-password"
            ),
        }
        sessions: dict[str, zenoh.Session | None] = {}
        stolen: dict[str, list[bytes]] = {}
        for name, values in attackers.items():
            sessions[name] = session = _open_or_none(endpoint, values)
            stolen[name] = []
            if session is not None:  # it got a session: may it read or write anything?
                session.declare_subscriber(f"srl/{ROBOT}/**", lambda s, n=name: stolen[n].append(b""))
        plain = _open_or_none(endpoint.replace("tls/", "tcp/"), {})  # no TLS at all
        time.sleep(0.5)
        for k in range(10):
            plant.put(f"srl/{ROBOT}/state", f"legit {k}".encode())
            for session in sessions.values():
                if session is not None:
                    session.put(f"srl/{ROBOT}/action", b"ROGUE")
            time.sleep(0.05)
        control = _session(endpoint, **_login(endpoint, secrets, tls, "actor"))  # the real actor, for contrast
        time.sleep(0.3)
        control.put(f"srl/{ROBOT}/action", b"legit action")
        wait_until(lambda: len(states) == 10 and actions == [b"legit action"], 10, "the legitimate traffic")
        time.sleep(0.3)
        for session in [*sessions.values(), plain, monitor, plant, control]:
            if session is not None:
                session.close()
        assert router.process.poll() is None
    opened = sorted(name for name, session in sessions.items() if session is not None)
    print(
        f"\nfigures: TLS+login router: {len(attackers) + 1} attackers, sessions opened {opened}, "
        f"samples they read {sum(len(v) for v in stolen.values())}, rogue actions delivered "
        f"{sum(a == b'ROGUE' for a in actions)}; legit states {len(states)}/10, legit actions {len(actions)}"
    )
    assert plain is None
    assert opened == []  # every one is refused at connection time (TLS handshake or login)
    assert actions == [b"legit action"] and all(not v for v in stolen.values())


@pytest.mark.integration
@pytest.mark.slow
def test_actor_critic_plant_run_over_mutual_tls(tmp_path: Path) -> None:
    with tls_router(tmp_path) as (endpoint, secrets, tls, router):
        common = ["--router", endpoint, "--robot", ROBOT]
        procs = [router]
        try:
            plant = Proc("plant", ["plant-sim", *common, "--mode", "realtime"], _role_env(secrets, tls, "plant"))
            critic = Proc("critic", ["critic", *common], _role_env(secrets, tls, "critic"))
            procs += [plant, critic]
            monitor = None

            def up() -> bool:
                nonlocal monitor
                monitor = monitor or _open_or_none(endpoint, _login(endpoint, secrets, tls, "monitor"))
                if monitor is None:
                    return False
                tokens = [r.ok for r in monitor.liveliness().get(f"srl/{ROBOT}/alive/*", timeout=0.5) if r.ok]
                return len(tokens) >= 2

            wait_until(up, 60, "plant and critic over TLS")
            actor = Proc(
                "actor",
                ["actor", *common, "--mode", "realtime", "--agent", "rlqv", "--run-seconds", "4", "--start=1.5,1"],
                _role_env(secrets, tls, "actor"),
            )
            procs.append(actor)
            actor.process.wait(timeout=180)
            assert actor.process.returncode == 0, actor.stderr[-10:]
            assert critic.stop() == 0 and plant.stop() == 0
            summary, critic_summary = actor.summary(), critic.summary()
            if monitor is not None:
                monitor.close()
        finally:
            for proc in procs[1:]:
                proc.stop()
    print(
        f"\nfigures: actor/critic/plant over {endpoint}: {summary['steps']} steps, "
        f"{critic_summary['transitions_received']} transitions at the critic, "
        f"weights version {summary['weights_version']}"
    )
    assert summary["steps"] >= 25
    assert critic_summary["transitions_received"] >= summary["steps"] - 1
    assert summary["weights_version"] > 0


def _readme_block(marker: str) -> str:
    # docs/security.md#add-a-host; a block's <!-- not run: ... --> line (tests/docs_blocks.py) may follow the marker
    text = (ROOT / "docs" / "security.md").read_text()
    match = re.search(rf"<!-- {marker} -->\s*(?:<!-- not run:.*?-->\s*)?```bash\n(.*?)```", text, re.S)
    assert match, f"docs/security.md has no ```bash block after <!-- {marker} -->"
    return match.group(1)


@pytest.mark.integration
@pytest.mark.slow
def test_readme_add_a_host_steps_work(tmp_path: Path) -> None:
    """The README's "add a host" commands, run as written. Substituted, and nothing else: the
    two machines become two directories (router-pc's home, new-host's home), ``robot-pc`` and
    ``0.0.0.0:7447`` the loopback address and a free port, ``ssh``/``scp`` a local shell and
    ``cp``, ``srl`` this checkout's Python."""
    port = free_port()
    router_home, new_home = tmp_path / "router-pc", tmp_path / "new-host"
    router_home.mkdir()
    new_home.mkdir()
    srl = f"{sys.executable} -m tools.cli"

    def local(block: str, home: Path) -> str:
        block = block.replace("robot-pc:7447", f"127.0.0.1:{port}").replace("0.0.0.0:7447", f"127.0.0.1:{port}")
        block = re.sub(
            r"ssh new-host '([^']*)'",  # runs on the new host: its ~
            lambda m: "bash -c '" + m.group(1).replace("~/", f"{new_home}/") + "'",
            block,
        )
        block = re.sub(r"scp (\S+) new-host:(\S+)", rf"cp \1 {new_home}/\2", block)
        block = re.sub(r"(^|\s)srl ", rf"\1{srl} ", block, flags=re.M)
        return block.replace("~/", f"{home}/")

    env = {**os.environ, "SRL_CRITIC__CHECKPOINT": "", "SRL_TRANSPORT__ROBOT": ROBOT}
    make = local(_readme_block("add-a-host: router"), router_home)
    lines = make.strip().splitlines()
    setup, router_cmd = "\n".join(lines[:-1]), lines[-1]
    done = subprocess.run(["bash", "-euc", setup], cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    router = subprocess.Popen(
        ["bash", "-euc", router_cmd],
        cwd=ROOT,
        text=True,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    host = None
    try:
        copy = local(_readme_block("add-a-host: copy"), router_home)
        done = subprocess.run(["bash", "-euc", copy], cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
        assert done.returncode == 0, done.stderr
        assert sorted(p.name for p in (new_home / "srl-secrets").iterdir()) == [
            "ca.pem",
            "critic.key",
            "critic.password",
            "critic.pem",
        ]  # nothing else left the router's machine
        run = local(_readme_block("add-a-host: new host"), new_home).strip().splitlines()
        run[-1] = f"exec {run[-1]}"  # the service is the shell's process: stopped by its pid
        host = subprocess.Popen(
            ["bash", "-euc", "\n".join(run)],
            cwd=ROOT,
            text=True,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        secrets = router_home / "srl-secrets"
        endpoint = f"tls/127.0.0.1:{port}"
        seen: list[str] = []

        def critic_alive() -> bool:
            assert host is not None and host.poll() is None, host.stderr.read() if host else ""
            session = _open_or_none(endpoint, _login(endpoint, secrets, secrets, "monitor"))
            if session is None:
                return False
            try:
                seen.extend(
                    str(r.ok.key_expr)
                    for r in session.liveliness().get(f"srl/{ROBOT}/alive/critic", timeout=0.5)
                    if r.ok
                )
            finally:
                session.close()
            return bool(seen)

        wait_until(critic_alive, 60, "the new host's critic, through the TLS router")
    finally:
        for proc in (host, router):
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, 2)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, 9)
                    proc.wait()
    print(f"\nfigures: README add-a-host: the new host's critic is alive through {endpoint}: {seen[0]}")
    assert seen == [f"srl/{ROBOT}/alive/critic"]
    assert json.loads(router.stdout.read().strip().splitlines()[-1])["endpoint"] == endpoint
