"""A real single-node Slurm for the tests: munged, slurmctld and slurmd from Debian's packages
(``munge``, ``slurmctld``, ``slurmd``, ``slurm-client``), run from a private directory.

Nothing of the machine's is used or changed: the daemons read a ``slurm.conf`` of their own
(``-f``; clients find it through ``SLURM_CONF``), munged runs as user munge with its own key,
socket, pid and seed files, and state, spool, pid and log files stay in the directory. The
daemons run in the foreground as children of the test (recorded ``Popen``s, stopped by PID, so
none is left to PID 1 to reap). Debian's init scripts never run.

Everything listens on loopback when the host's name resolves to a loopback address (Debian's
``127.0.0.1`` or ``127.0.1.1`` line): Slurm's ``NoCtldInAddrAny``/``NoInAddrAny`` bind its
daemons to that address. A host whose name resolves to nothing (a bare debootstrap root has no
``/etc/hosts``) or elsewhere gets ``NodeAddr=127.0.0.1`` instead: the daemons then listen on
every address, on ports picked at random, for the seconds the test lasts, and are only ever
reached on 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import re
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from types import TracebackType
from typing import Self

from needs import end_process, missing, require_binary

__all__ = ["PARTITION", "SingleNodeSlurm"]

#: The cluster's one partition.
PARTITION = "studies"
#: Seconds for munged to create its socket and for slurmd to register with slurmctld and the
#: node to go idle: about 1 s here; a loaded 2-core CI machine gets a wide margin.
START_TIMEOUT = 60.0
#: Seconds for a daemon to stop after SIGTERM (slurmctld saves its state first), then SIGKILL.
STOP_TIMEOUT = 20.0
#: Seconds for the jobs left at the end to be cancelled (scancel, then slurmstepd ends them:
#: SIGTERM, and SIGKILL after the configured KillWait).
CANCEL_TIMEOUT = 30.0
#: KillWait: seconds between a cancelled job's SIGTERM and SIGKILL (Slurm's default is 30).
KILL_WAIT = 5
#: Memory a job without --mem gets per CPU, in MB: without it such a job takes the whole node.
DEF_MEM_PER_CPU = 512

#: (program, Debian package) of everything the cluster needs.
PROGRAMS = (
    ("munged", "munge"),
    ("slurmctld", "slurmctld"),
    ("slurmd", "slurmd"),
    ("sbatch", "slurm-client"),
    ("sinfo", "slurm-client"),
    ("squeue", "slurm-client"),
    ("scancel", "slurm-client"),
    ("scontrol", "slurm-client"),
)


def _free_ports(count: int, address: str) -> list[int]:
    # Ports free on ``address`` now, all different; Slurm's daemons take fixed ports from
    # slurm.conf, and the defaults (6817, 6818) may be taken by another test's cluster or a real
    # Slurm. (Probed on the address a daemon binds: a port free on 127.0.0.1 may be taken on
    # another.) Nothing listens on the probes.
    probes = [socket.socket() for _ in range(count)]
    try:
        for probe in probes:
            probe.bind((address, 0))
        return [probe.getsockname()[1] for probe in probes]
    finally:
        for probe in probes:
            probe.close()


def _loopback_name() -> tuple[str, str | None]:
    """The host's short name, and the loopback address it resolves to (None if it resolves to
    none: nothing, or an address elsewhere)."""
    name = socket.gethostname().split(".")[0]
    try:
        address = socket.gethostbyname(socket.gethostname())
    except OSError:
        return name, None
    return name, address if address.startswith("127.") else None


class SingleNodeSlurm:
    """A single-node Slurm cluster in a private directory; a context manager.

    ``env`` holds ``SLURM_CONF`` for every Slurm client (sbatch, squeue, dask-jobqueue); the
    node has the machine's cores and memory (``slurmd -C``) in one partition, :data:`PARTITION`.
    """

    def __init__(self) -> None:
        if os.geteuid() != 0:
            missing("a Slurm cluster for the tests needs root (slurmd runs the jobs as their user)")
        self.programs = {name: require_binary(name, package) for name, package in PROGRAMS}
        try:
            self._munge = pwd.getpwnam("munge")
        except KeyError:
            missing("the user munge does not exist (apt-get install munge)")
        # Not below pytest's tmp_path: munged runs as munge and refuses a socket or key whose
        # directories it cannot traverse or that others may write (pytest's are root's, 0700).
        self.dir = Path(tempfile.mkdtemp(prefix="slurm-test-"))
        self.dir.chmod(0o755)
        self.conf = self.dir / "slurm.conf"
        self.env = {**os.environ, "SLURM_CONF": str(self.conf)}
        self.node, self.address = _loopback_name()
        self._processes: dict[str, subprocess.Popen[bytes]] = {}

    def __enter__(self) -> Self:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

    # ------------------------------------------------------------------------------ start

    def start(self) -> None:
        """Start munged, slurmctld and slurmd; return once the node takes jobs."""
        self._start_munge()
        self.conf.write_text(self._slurm_conf())
        for name in ("state", "spool", "log"):
            (self.dir / name).mkdir()
        self._spawn("slurmctld", [self.programs["slurmctld"], "-D", "-f", str(self.conf)])
        self._spawn(
            "slurmd", [self.programs["slurmd"], "-D", "-f", str(self.conf), "-N", self.node]
        )
        self._wait(self._idle, "the node to take jobs (sinfo: idle)")

    def _start_munge(self) -> None:
        folder = self.dir / "munge"
        folder.mkdir(mode=0o755)  # munged wants its socket's directory searchable by all
        key = folder / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)  # munged refuses a key that its group or others may read
        for path in (folder, key):
            os.chown(path, self._munge.pw_uid, self._munge.pw_gid)
        self.munge_socket = folder / "munge.socket"
        self._spawn(
            "munged",
            [
                self.programs["munged"], "--foreground",
                f"--socket={self.munge_socket}", f"--key-file={key}",
                f"--pid-file={folder / 'munged.pid'}", f"--log-file={folder / 'munged.log'}",
                f"--seed-file={folder / 'munged.seed'}",
            ],
            # As root munged refuses to start ("PRNG seed dir is insecure").
            user=self._munge.pw_uid, group=self._munge.pw_gid, extra_groups=[],
        )  # fmt: skip
        self._wait(self.munge_socket.exists, "munged to create its socket")

    def _slurm_conf(self) -> str:
        hardware = subprocess.run(
            [self.programs["slurmd"], "-C"], capture_output=True, text=True, check=True
        ).stdout.splitlines()[0]
        # "NodeName=vm CPUs=2 Boards=1 ... RealMemory=24105": the node's line without its name.
        hardware = re.sub(r"^NodeName=\S+\s*", "", hardware)
        if self.address is not None:
            address, listen = self.address, "CommunicationParameters=NoCtldInAddrAny,NoInAddrAny"
            bound = self.address
        else:
            address, listen = "127.0.0.1", "# the host's name is not on loopback: listen on any"
            bound = ""
        ctld_port, node_port = _free_ports(2, bound)
        d = self.dir
        return f"""\
ClusterName=studies-test
SlurmctldHost={self.node}({address})
SlurmctldPort={ctld_port}
SlurmdPort={node_port}
{listen}
SlurmUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={self.munge_socket}
# No cgroups in a container without systemd: the default proctrack/cgroup fails there.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
MailProg=/bin/true
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
DefMemPerCPU={DEF_MEM_PER_CPU}
ReturnToService=2
KillWait={KILL_WAIT}
StateSaveLocation={d / "state"}
SlurmdSpoolDir={d / "spool"}
SlurmctldPidFile={d / "slurmctld.pid"}
SlurmdPidFile={d / "slurmd.pid"}
SlurmctldLogFile={d / "log" / "slurmctld.log"}
SlurmdLogFile={d / "log" / "slurmd.log"}
NodeName={self.node} NodeAddr={address} {hardware} State=UNKNOWN
PartitionName={PARTITION} Nodes={self.node} Default=YES MaxTime=INFINITE State=UP
"""

    def _spawn(self, name: str, args: list[str], **options) -> None:
        with open(self.dir / f"{name}.out", "wb") as log:
            self._processes[name] = subprocess.Popen(
                args, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                env=self.env, **options,
            )  # fmt: skip

    def _wait(self, ready, what: str) -> None:
        deadline = time.monotonic() + START_TIMEOUT
        while not ready():
            for name, process in self._processes.items():
                if process.poll() is not None:
                    raise RuntimeError(f"{name} ended ({process.returncode}): {self.log(name)}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"waited {START_TIMEOUT:g} s for {what}: {self.logs()}")
            time.sleep(0.1)

    def _idle(self) -> bool:
        return self.run("sinfo", "-h", "-o", "%t", check=False).stdout.strip() == "idle"

    # ------------------------------------------------------------------------------ use

    def run(self, program: str, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        """Run a Slurm client (``sbatch``, ``squeue``, ...) against this cluster."""
        return subprocess.run(
            [self.programs[program], *args], env=self.env, capture_output=True, text=True,
            check=check, timeout=START_TIMEOUT,
        )  # fmt: skip

    def jobs(self) -> dict[str, str]:
        """Job id -> state of every job Slurm still lists (finished ones for MinJobAge)."""
        out = self.run("scontrol", "-o", "show", "jobs").stdout
        return dict(re.findall(r"JobId=(\d+) .*?JobState=(\S+)", out))

    def log(self, name: str, lines: int = 15) -> str:
        """The last lines a daemon printed."""
        with contextlib.suppress(OSError):
            text = (self.dir / f"{name}.out").read_text(errors="replace")
            return "\n".join(text.splitlines()[-lines:])
        return ""

    def logs(self) -> str:
        """Every daemon's last lines, for a failure's message."""
        return "\n".join(f"--- {name}:\n{self.log(name)}" for name in self._processes)

    # ------------------------------------------------------------------------------ stop

    def stop(self) -> None:
        """Cancel the jobs left, stop the daemons (by their recorded PIDs), remove the files."""
        if "slurmd" in self._processes and self._processes["slurmd"].poll() is None:
            # A job's processes belong to slurmstepd, not to slurmd: they would outlive it.
            with contextlib.suppress(subprocess.SubprocessError, OSError):
                self.run("scancel", f"--partition={PARTITION}", check=False)
                deadline = time.monotonic() + CANCEL_TIMEOUT
                while time.monotonic() < deadline and any(
                    state in ("PENDING", "RUNNING", "COMPLETING", "CONFIGURING")
                    for state in self.jobs().values()
                ):
                    time.sleep(0.2)
        for name in ("slurmd", "slurmctld", "munged"):
            end_process(self._processes.pop(name, None), STOP_TIMEOUT)
        shutil.rmtree(self.dir, ignore_errors=True)
