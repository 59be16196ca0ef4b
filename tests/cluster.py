"""A real one-node SLURM cluster (munge, MariaDB, slurmdbd, slurmctld, slurmd) and a local sshd, for the tests.

Everything runs as children of the test process, in the foreground, with its configuration, sockets, spool,
state, database and logs under one temporary folder and on private ports, so nothing on the machine is touched
and :meth:`Daemons.stop` ends exactly what was started. Debian's packages provide the programs
(``make test`` installs them as root: slurm-wlm, slurmdbd, munge, mariadb-server, openssh-server); where they are
missing or do not start, :func:`start_slurm` and :func:`start_sshd` raise :class:`Unavailable` with the reason,
which the fixtures turn into a skip.

Accounting is real (slurmdbd on MariaDB), as on a lab's cluster: snakemake-executor-plugin-slurm reads job
states with ``sacct`` by default, and ``sacct`` is where every job's request, state and peak memory stay after
it ends.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

CLUSTER = "vtgentest"
# snakemake-executor-plugin-slurm-jobstep (0.6.1) drops SLURM_CONF from the environment of the srun it starts inside
# each job, so that srun finds the configuration only at the compiled-in path: the test cluster links its
# configuration there (only where no slurm.conf exists) and removes the link when it stops.
SYSTEM_CONF = Path("/etc/slurm/slurm.conf")
ACCOUNT = "vtgen"
PARTITION = "cpu"


class Unavailable(RuntimeError):
    """The cluster (or sshd) cannot be installed or started here; the message says why."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _need(*programs: str) -> None:
    missing = [p for p in programs if shutil.which(p) is None and not Path("/usr/sbin", p).exists()]
    if missing:
        raise Unavailable(f"not installed: {', '.join(missing)} (Debian: `make test` installs them as root)")
    if os.geteuid() != 0:
        raise Unavailable("the test cluster runs its daemons as root (SlurmUser=root); not root here")


def _which(program: str) -> str:
    return shutil.which(program) or str(Path("/usr/sbin", program))


@dataclass
class Daemons:
    """Foreground daemons started by a test; :meth:`stop` ends them (last started first), whatever state they are in."""

    root: Path
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, name: str, cmd: list[str], env: dict | None = None) -> subprocess.Popen:
        log = open(self.root / f"{name}.out", "ab")
        self.processes[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                                start_new_session=True)
        log.close()
        return self.processes[name]

    def alive(self, name: str) -> bool:
        return name in self.processes and self.processes[name].poll() is None

    def stop_one(self, name: str, timeout: float = 20) -> None:
        process = self.processes.pop(name, None)
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)

    def stop(self) -> None:
        for name in reversed(list(self.processes)):
            self.stop_one(name)

    def log(self, name: str, tail: int = 2000) -> str:
        path = self.root / f"{name}.out"
        text = path.read_text(errors="replace") if path.is_file() else ""
        logfile = self.root / "log" / f"{name}.log"
        if logfile.is_file():
            text += logfile.read_text(errors="replace")
        return text[-tail:]


def end_job_leftovers(submit_dir: Path) -> list[int]:
    """SIGKILL every process of a SLURM job submitted from ``submit_dir`` (its environment's ``SLURM_SUBMIT_DIR``)
    that outlived its job; returns their pids. The test cluster tracks a job's processes by parent
    (``proctrack/linuxproc``), so a child whose parent ended first (a training under a cancelled Snakemake job
    step) is no longer found when the job is cancelled, and would load every later test (a site's
    ``proctrack/cgroup`` does not lose them)."""
    wanted = f"SLURM_SUBMIT_DIR={submit_dir}".encode()
    ended = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if wanted in (entry / "environ").read_bytes().split(b"\0"):
                os.kill(int(entry.name), signal.SIGKILL)
                ended.append(int(entry.name))
        except OSError:
            continue  # ended meanwhile, or not ours to read
    return ended


def wait_for(check, what: str, timeout: float, daemons: Daemons | None = None, names: tuple = ()) -> None:
    """Poll ``check()`` until true; raise Unavailable naming ``what`` (and the logs of ``names``) on time-out or death."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        for name in names:
            if daemons is not None and not daemons.alive(name):
                raise Unavailable(f"{name} exited while waiting for {what}:\n{daemons.log(name)}")
        time.sleep(0.3)
    logs = "\n".join(f"--- {n}:\n{daemons.log(n)}" for n in names) if daemons else ""
    raise Unavailable(f"timed out after {timeout:.0f} s waiting for {what}\n{logs}")


@dataclass
class Slurm:
    """A running one-node cluster: ``env`` points the SLURM commands (sbatch, sacct, ...) at it."""

    root: Path
    daemons: Daemons
    env: dict
    node: str
    cpus: int
    memory_mb: int

    def command(self, *args: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess:
        result = subprocess.run(list(args), env=self.env, capture_output=True, text=True, timeout=timeout)
        if check and result.returncode != 0:
            raise RuntimeError(f"{' '.join(args)} failed ({result.returncode}): {result.stderr.strip()}")
        return result

    def node_state(self) -> str:
        result = self.command("sinfo", "--noheader", "--nodes", self.node, "--format=%T", check=False)
        return result.stdout.strip() if result.returncode == 0 else ""

    def wait_idle(self, timeout: float = 60) -> None:
        wait_for(lambda: self.node_state() == "idle", f"sinfo to show node {self.node} idle", timeout,
                 self.daemons, ("slurmctld", "slurmd"))

    def start_slurmd(self) -> None:
        self.daemons.start("slurmd", [_which("slurmd"), "-D", "-N", self.node], self.env)

    def restart_slurmd(self) -> None:
        """Stop slurmd (SIGTERM, as `systemctl restart` does) and start it again; running jobs are left alone."""
        self.daemons.stop_one("slurmd")
        self.start_slurmd()

    def jobs(self, run_uuid: str | None = None) -> list[dict]:
        """Every job in the accounting records (sacct), optionally only those named ``run_uuid`` (a Snakemake run)."""
        fields = "JobIDRaw,JobName,State,ExitCode,Partition,Account,ReqCPUS,ReqMem,Timelimit,Elapsed,Comment,MaxRSS"
        args = ["sacct", "--allusers", "--parsable2", "--noheader", "--duplicates", f"--format={fields}",
                "--starttime", "2000-01-01"]
        if run_uuid:
            args += ["--name", run_uuid]
        rows = [dict(zip(fields.split(","), line.split("|"))) for line in self.command(*args).stdout.splitlines()]
        return rows

    def stop(self) -> None:
        """Cancel every job still queued or running (their processes end with them), then stop the daemons."""
        try:
            if self.daemons.alive("slurmctld"):
                self.command("scancel", "--full", "--user=root", check=False, timeout=30)
                wait_for(lambda: not self.command("squeue", "--noheader", check=False, timeout=30).stdout.strip(),
                         "the cancelled jobs to end", 30)
        except (Unavailable, subprocess.TimeoutExpired):
            pass  # stop the daemons all the same
        finally:
            self.daemons.stop()
            _unlink_system_conf(self.root / "slurm.conf")


def _slurm_conf(root: Path, node: str, cpus: int, memory_mb: int, ports: dict) -> str:
    return f"""# a one-node test cluster written by tests/cluster.py
ClusterName={CLUSTER}
SlurmctldHost={node}(127.0.0.1)
SlurmctldPort={ports['ctld']}
SlurmdPort={ports['slurmd']}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
StateSaveLocation={root}/state
SlurmdSpoolDir={root}/spool/%n
SlurmctldPidFile={root}/run/slurmctld.pid
SlurmdPidFile={root}/run/slurmd.pid
SlurmctldLogFile={root}/log/slurmctld.log
SlurmdLogFile={root}/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=task=2
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
AccountingStoragePort={ports['dbd']}
AccountingStoreFlags=job_comment
MinJobAge=300
SlurmdTimeout=60
InactiveLimit=0
KillWait=5
NodeName={node} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN
PartitionName={PARTITION} Nodes={node} Default=YES MaxTime=INFINITE State=UP
"""


def _node_hardware() -> tuple[str, int, int]:
    """This host's short name, CPUs and usable memory in MB, as slurmd itself measures them (`slurmd -C`)."""
    out = subprocess.run([_which("slurmd"), "-C"], capture_output=True, text=True, timeout=30).stdout
    fields = dict(item.split("=", 1) for item in out.split() if "=" in item)
    try:
        return fields["NodeName"], int(fields["CPUs"]), int(fields["RealMemory"])
    except KeyError as exc:
        raise Unavailable(f"`slurmd -C` did not describe this host: {out!r}") from exc


MUNGE_SOCKET = Path("/run/munge/munge.socket.2")  # where sacctmgr looks, whatever AuthInfo says (seen on 22.05)


def _munge_answers() -> bool:
    encode = subprocess.run(["munge", "-n", f"--socket={MUNGE_SOCKET}"], capture_output=True)
    return encode.returncode == 0 and subprocess.run(
        ["unmunge", f"--socket={MUNGE_SOCKET}"], input=encode.stdout, capture_output=True).returncode == 0


def _start_munge(root: Path, daemons: Daemons) -> None:
    """munged on its default socket with a key made here, unless a munged already answers there (then use it)."""
    if MUNGE_SOCKET.exists() and _munge_answers():
        return
    folder = root / "munge"
    folder.mkdir(mode=0o700)
    key = folder / "munge.key"
    subprocess.run([_which("mungekey"), "--create", f"--keyfile={key}"], check=True, capture_output=True)
    key.chmod(0o400)
    MUNGE_SOCKET.parent.mkdir(parents=True, exist_ok=True)
    daemons.start("munged", [_which("munged"), "--foreground", "--force", f"--key-file={key}",
                             f"--socket={MUNGE_SOCKET}", f"--pid-file={folder}/munged.pid",
                             f"--log-file={root}/log/munged.log", f"--seed-file={folder}/munged.seed"])
    wait_for(_munge_answers, "munged to answer", 20, daemons, ("munged",))


def _start_mariadb(root: Path, daemons: Daemons) -> tuple[int, str]:
    """MariaDB on a private port with a `slurm` user for slurmdbd; returns (port, password)."""
    data = root / "mysql"
    install = subprocess.run([_which("mariadb-install-db"), f"--datadir={data}", "--user=root",
                              "--auth-root-authentication-method=socket", "--skip-test-db"],
                             capture_output=True, text=True, timeout=120)
    if install.returncode != 0:
        raise Unavailable(f"mariadb-install-db failed: {install.stderr[-1500:]}")
    port, sock = free_port(), root / "mysql.sock"
    daemons.start("mariadbd", [_which("mariadbd"), "--no-defaults", f"--datadir={data}", "--user=root",
                               f"--socket={sock}", f"--port={port}", "--bind-address=127.0.0.1",
                               f"--pid-file={root}/run/mariadbd.pid", "--innodb-buffer-pool-size=32M",
                               "--skip-log-bin", "--innodb-log-file-size=16M"])
    wait_for(lambda: sock.exists(), "MariaDB's socket", 60, daemons, ("mariadbd",))
    password = "vtgen-test"
    sql = (f"CREATE USER 'slurm'@'127.0.0.1' IDENTIFIED BY '{password}'; "
           "GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1'; FLUSH PRIVILEGES;")
    client = shutil.which("mariadb") or "mysql"
    for _ in range(50):
        result = subprocess.run([client, "--no-defaults", f"--socket={sock}", "-uroot", "-e", sql],
                                capture_output=True, text=True)
        if result.returncode == 0:
            return port, password
        time.sleep(0.3)
    raise Unavailable(f"could not create MariaDB's slurm user: {result.stderr}")


def start_slurm(root: Path) -> Slurm:
    """Start munged, MariaDB, slurmdbd, slurmctld and slurmd under ``root``; return once the node is idle.

    Stops whatever it started and raises :class:`Unavailable` if any part does not come up."""
    _need("munged", "mungekey", "slurmctld", "slurmd", "slurmdbd", "sbatch", "sacct", "sacctmgr", "mariadbd",
          "mariadb-install-db")
    node, cpus, memory_mb = _node_hardware()
    for sub in ("log", "run", "state", "spool"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    daemons = Daemons(root)
    try:
        _start_munge(root, daemons)
        db_port, password = _start_mariadb(root, daemons)
        ports = {"ctld": free_port(), "slurmd": free_port(), "dbd": free_port()}
        (root / "slurm.conf").write_text(_slurm_conf(root, node, cpus, memory_mb, ports))
        _link_system_conf(root / "slurm.conf")
        dbd_conf = root / "slurmdbd.conf"
        dbd_conf.write_text(
            f"AuthType=auth/munge\nDbdHost=localhost\nDbdAddr=127.0.0.1\n"
            f"DbdPort={ports['dbd']}\nSlurmUser=root\nPidFile={root}/run/slurmdbd.pid\n"
            f"LogFile={root}/log/slurmdbd.log\nStorageType=accounting_storage/mysql\nStorageHost=127.0.0.1\n"
            f"StoragePort={db_port}\nStorageUser=slurm\nStoragePass={password}\nStorageLoc=slurm_acct_db\n")
        dbd_conf.chmod(0o600)
        env = {**os.environ, "SLURM_CONF": str(root / "slurm.conf")}
        for name in list(env):  # a test run inside a SLURM job must not leak that job's settings into the submissions
            if name.startswith(("SLURM_", "SBATCH_", "SALLOC_", "SRUN_")) and name != "SLURM_CONF":
                env.pop(name)
        daemons.start("slurmdbd", [_which("slurmdbd"), "-D"], env)  # reads slurmdbd.conf beside SLURM_CONF
        slurm = Slurm(root, daemons, env, node, cpus, memory_mb)
        wait_for(lambda: slurm.command("sacctmgr", "--noheader", "list", "cluster", check=False).returncode == 0,
                 "slurmdbd to answer sacctmgr", 60, daemons, ("slurmdbd",))
        for entity in (["cluster", CLUSTER], ["account", ACCOUNT, f"cluster={CLUSTER}"],
                       ["user", "root", f"account={ACCOUNT}", f"cluster={CLUSTER}"]):
            slurm.command("sacctmgr", "--immediate", "add", *entity)
        daemons.start("slurmctld", [_which("slurmctld"), "-D", "-i"], env)
        slurm.start_slurmd()
        slurm.wait_idle(90)
        return slurm
    except BaseException:
        daemons.stop()
        _unlink_system_conf(root / "slurm.conf")
        raise


def _link_system_conf(conf: Path) -> None:
    if SYSTEM_CONF.is_symlink() and (not SYSTEM_CONF.exists() or _stale_test_conf(SYSTEM_CONF)):
        SYSTEM_CONF.unlink()  # left behind by a test run that was killed (its folder gone, or kept by pytest)
    if SYSTEM_CONF.exists() or SYSTEM_CONF.is_symlink():
        raise Unavailable(f"{SYSTEM_CONF} exists (a real SLURM here?); the test cluster would need that path")
    SYSTEM_CONF.parent.mkdir(parents=True, exist_ok=True)
    SYSTEM_CONF.symlink_to(conf)


def _stale_test_conf(conf: Path) -> bool:
    """Whether ``conf`` is a test cluster's configuration (the first line :func:`_slurm_conf` writes) whose
    slurmctld no longer runs (its pid file gone or naming no process): a killed run's, safe to replace."""
    try:
        text = conf.read_text()
    except OSError:
        return False
    if not text.startswith("# a one-node test cluster written by tests/cluster.py"):
        return False
    pid_file = next((Path(line.split("=", 1)[1]) for line in text.splitlines()
                     if line.startswith("SlurmctldPidFile=")), None)
    try:
        os.kill(int(pid_file.read_text().strip()), 0)
    except (AttributeError, OSError, ValueError):
        return True
    return False


def _unlink_system_conf(conf: Path) -> None:
    if SYSTEM_CONF.is_symlink() and Path(os.readlink(SYSTEM_CONF)) == conf:
        SYSTEM_CONF.unlink()


def start_sshd(root: Path) -> tuple[Daemons, int, Path]:
    """sshd on a loopback port that accepts only a key made here; returns (daemons, port, private key)."""
    _need("sshd", "ssh-keygen")
    root.mkdir(parents=True, exist_ok=True)
    key, host_key = root / "id_ed25519", root / "host_ed25519"
    for path in (key, host_key):
        subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(path)], check=True)
    (root / "authorized_keys").write_text((root / "id_ed25519.pub").read_text())
    (root / "authorized_keys").chmod(0o600)
    port = free_port()
    config = root / "sshd_config"
    config.write_text(
        f"Port {port}\nListenAddress 127.0.0.1\nHostKey {host_key}\nPidFile {root}/sshd.pid\n"
        f"AuthorizedKeysFile {root}/authorized_keys\nPasswordAuthentication no\nKbdInteractiveAuthentication no\n"
        "PubkeyAuthentication yes\nPermitRootLogin prohibit-password\nStrictModes no\nUsePAM no\n"
        "Subsystem sftp internal-sftp\n")
    Path("/run/sshd").mkdir(exist_ok=True)  # sshd's privilege separation folder
    daemons = Daemons(root)
    daemons.start("sshd", [_which("sshd"), "-D", "-e", "-f", str(config)])

    def listening() -> bool:
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", port)) == 0

    try:
        wait_for(listening, "sshd to listen", 20, daemons, ("sshd",))
    except BaseException:
        daemons.stop()
        raise
    return daemons, port, key
