"""Issue 22, item 1: one owner per physical device, whatever its spelling, the environment of the
process asking, or its user; and the OS's exclusive open on serial ports."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

import drivers
from drivers.device_identity import identify
from drivers.errors import Disconnected
from drivers.ownership import DeviceBusy, claim, held_keys, release
from drivers.testing import fast_sim_rig
from drivers.transport import LineTransport
from lab.core import locks
from lab.core.errors import UserError

# a process that claims the turntable at argv[1] and reports what happened (its environment is the
# test's to choose)
_CLAIM = ("import sys, drivers\n"
          "from drivers.testing import fast_sim_rig\n"
          "rig = fast_sim_rig().with_urls({'turntable': sys.argv[1]})\n"
          "try:\n    drivers.connect(rig, only=['turntable'])\nexcept Exception as e:\n"
          "    print(type(e).__name__, e); sys.exit(0)\nprint('claimed'); sys.exit(5)\n")


def _claim_elsewhere(url: str, env: dict[str, str] | None = None) -> str:
    r = subprocess.run([sys.executable, "-c", _CLAIM, url], capture_output=True, text=True, timeout=60,
                       env={**os.environ, **(env or {})})
    return r.stdout.strip() + r.stderr.strip()


@pytest.mark.parametrize("spelling", ["socket://localhost:{p}", "socket://127.1:{p}", "socket://[::1]:{p}",
                                      "socket://LOCALHOST:{p}", "socket://0.0.0.0:{p}", "socket://127.0.0.1:{p}"])
def test_every_spelling_of_a_loopback_endpoint_is_one_device(spelling):
    assert identify(spelling.format(p=27101)).keys == identify("socket://127.0.0.1:27101").keys
    assert identify(spelling.format(p=27102)).keys != identify("socket://127.0.0.1:27101").keys   # the port counts


def test_http_and_socket_urls_of_one_endpoint_are_one_device_and_remote_hosts_keep_their_address():
    assert identify("http://localhost:8080/frame.jpg").keys == identify("socket://127.0.0.1:8080").keys
    assert identify("http://127.0.0.1").keys == identify("http://localhost:80/x").keys       # default port
    assert identify("socket://10.1.2.3:5").keys == ("tcp:10.1.2.3:5",)
    assert identify("http://[::ffff:10.1.2.3]:5").keys == ("tcp:10.1.2.3:5",)              # IPv4-mapped IPv6
    assert identify("http://no-such-host.invalid:80").keys == ("tcp:no-such-host.invalid:80",)


def test_a_serial_port_is_its_device_not_its_name(tmp_path):
    master, slave = os.openpty()
    try:
        path = os.ttyname(slave)
        link = tmp_path / "usb-LAB_RT1-if00-port0"
        link.symlink_to(path)
        chain = tmp_path / "ttyBENCH"
        chain.symlink_to(link)
        key = identify(path).keys
        assert key[0].startswith("tty:") and identify(str(link)).keys == key == identify(str(chain)).keys
        assert identify(str(tmp_path / "ttyNONE")).keys == (f"serial:{tmp_path / 'ttyNONE'}",)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("env", [{"XDG_RUNTIME_DIR": "{tmp}/xdg"}, {"TMPDIR": "{tmp}/tmp"},
                                 {"LAB_RUNTIME_DIR": "{tmp}/lab"}])
def test_another_environment_or_spelling_is_refused_naming_the_holder(tmp_path, env):
    env = {k: v.format(tmp=tmp_path) for k, v in env.items()}
    for d in env.values():
        Path(d).mkdir()
    with drivers.connect(fast_sim_rig().with_urls({"turntable": "socket://127.0.0.1:3"}), only=["turntable"]):
        got = _claim_elsewhere("socket://localhost:3", env)
        assert got.startswith("DeviceBusy device turntable (socket://localhost:3"), got
        assert f"pid {os.getpid()}" in got and "which holds it as device turntable (socket://127.0.0.1:3" in got
        assert "nothing was moved or stopped" in got
    assert _claim_elsewhere("socket://localhost:3", env) == "claimed"      # released with its holder


def test_the_lock_directory_is_machine_wide_and_open_to_every_user():
    with drivers.connect(fast_sim_rig().with_urls({"turntable": "socket://127.0.0.1:4"}), only=["turntable"]):
        d = locks.device_lock_dir()
        assert d in (locks.RUN_LOCK / "lab", locks.FALLBACK_LOCK_DIR)
        assert stat.S_IMODE(os.stat(d).st_mode) == 0o1777
        path = locks.device_lock_path("tcp:local:4")
        assert path.parent == d and stat.S_IMODE(os.stat(path).st_mode) == 0o666


def test_the_lock_directory_depends_on_the_machine_not_the_asker(tmp_path, monkeypatch):
    run_lock, fallback = tmp_path / "run-lock", tmp_path / "tmp-locks"
    run_lock.mkdir()
    monkeypatch.setattr(locks, "RUN_LOCK", run_lock)
    monkeypatch.setattr(locks, "FALLBACK_LOCK_DIR", fallback)
    os.chmod(run_lock, 0o755)                 # root's own (Fedora): every user falls back alike
    assert locks.device_lock_dir() == fallback
    os.chmod(run_lock, 0o1777)                # the FHS's shared lock directory
    assert locks.device_lock_dir() == run_lock / "lab"
    assert stat.S_IMODE(os.stat(run_lock / "lab").st_mode) == 0o1777
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.setenv("LAB_RUNTIME_DIR", str(tmp_path))
    assert locks.device_lock_dir() == run_lock / "lab"


def test_a_symlink_in_place_of_the_lock_directory_is_a_one_line_error(tmp_path, monkeypatch):
    monkeypatch.setattr(locks, "RUN_LOCK", tmp_path / "absent")
    monkeypatch.setattr(locks, "FALLBACK_LOCK_DIR", tmp_path / "locks")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "locks").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(UserError, match="is not a directory"):
        locks.device_lock_dir()


def test_aliases_in_one_process_share_one_claim():
    a = claim("turntable", "socket://127.0.0.1:5")
    b = claim("turntable", "socket://localhost:5")
    assert a == b == ["tcp:local:5"] and "tcp:local:5" in held_keys()
    release(a[0])
    assert "tcp:local:5" in held_keys()
    release(b[0])
    assert "tcp:local:5" not in held_keys()


def test_a_serial_port_held_under_its_path_is_refused_through_a_symlink(tmp_path):
    """/dev/ttyUSB0 against its /dev/serial/by-id link: here a pty and a symlink to it."""
    from sim_devices.bench import start_sim_bench

    with start_sim_bench(fast_sim_rig(), speedup=200, pty=True) as bench:
        path = bench.pty_paths["turntable"]
        link = tmp_path / "usb-LAB_RT1-if00-port0"
        link.symlink_to(path)
        with drivers.connect(bench.rig.with_urls({"turntable": path}), only=["turntable"]) as devs:
            assert devs.turntable.identify().startswith("TURNTABLE")
            got = _claim_elsewhere(str(link))
            assert got.startswith(f"DeviceBusy device turntable ({link}: {os.path.realpath(path)}"), got
            # and a process that skips the lock meets the OS's exclusive open
            sneak = LineTransport("turntable", str(link), reply_timeout_s=0.3, retries=0)
            with pytest.raises(Disconnected, match="exclusive"):
                sneak.open()


@pytest.mark.skipif(os.getuid() != 0, reason="acting as a second user needs root")
def test_a_lock_held_by_one_user_refuses_another():
    """The lock file another user created must be open to this one (mode 0666 in a 1777
    directory), and the refusal names the holding user."""
    import pwd

    from lab.studies.bench_faults_links import _as_user

    nobody = pwd.getpwnam("nobody").pw_uid
    url = "socket://127.0.0.1:6"

    def take() -> str:
        claim("turntable", url)
        return "ok held"

    pid, result = _as_user(nobody, take, hold_s=30)
    try:
        assert result() == "ok held"
        with pytest.raises(DeviceBusy, match="of user nobody"):
            claim("turntable", "socket://localhost:6")
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    # root holds it now (another process: a forked child would share this one's lock), nobody asks
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from drivers.ownership import claim\n"
                               f"claim('turntable', {url!r}); print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"

        def ask() -> str:
            try:
                claim("turntable", "socket://127.1:6")
            except DeviceBusy as exc:
                return f"refused {exc}"
            return "claimed"

        pid, result = _as_user(nobody, ask)
        text = result()
        os.waitpid(pid, 0)
        assert text.startswith("refused device turntable") and f"pid {holder.pid}" in text, text
    finally:
        holder.kill()
        holder.wait()
