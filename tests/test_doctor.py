"""`drums doctor` against this machine, and the attach-path choice against imagined kernels."""
import subprocess
import sys

from drums.kernel.features import Features
from drums.probes.bpf import choose_path
from drums.probes.sockets import SocketsProbe


class Kernel(Features):
    """A kernel described by hand: which tracepoints, kprobes and fentry it has, and whether its
    BTF types its tracepoints (Linux >= 5.5)."""

    def __init__(self, tracepoints=(), kprobes=False, fentry=False, tp_btf=True):
        super().__init__()
        self._tracepoints = set(tracepoints)
        self.__dict__["kprobes"] = kprobes
        self.__dict__["fentry"] = fentry
        self.__dict__["tp_btf"] = tp_btf

    def tracepoint(self, event):
        return event in self._tracepoints


# What every kernel of interest has (splice's syscall tracepoints among them, for --splice-tracepoints), and
# what 6.6 added.
LIFECYCLE = {"inet_sock_set_state", "sched_process_exit", "sched_process_free", "sched_process_exec",
             "sys_enter_splice", "sys_exit_splice"}
LINUX_6_6 = LIFECYCLE | {"sock_send_length", "sock_recv_length"}


def chosen(kernel):
    path, reasons = choose_path(SocketsProbe.paths, kernel)
    return (path.name if path else None), reasons


def test_new_kernel_uses_socket_tracepoints_even_with_kprobes_and_fentry():
    assert chosen(Kernel(LINUX_6_6, kprobes=True, fentry=True)) == ("tp_btf", [])
    assert chosen(Kernel(LINUX_6_6, kprobes=True, fentry=True, tp_btf=False)) == (
        "raw_tracepoint", ["tp_btf: the kernel's BTF does not type its tracepoints (Linux >= 5.5)"])


def test_splice_reads_on_the_tracepoint_paths_cost_every_system_call_only_when_asked():
    """Kprobes count what splice takes from a socket where the kernel has them; without, nothing
    does unless the agent is told to pay for the syscall tracepoints, and doctor says which."""
    from drums.proctable import ProcessTable
    from drums.probes import sockets
    tp_btf = SocketsProbe.paths[0]
    fentry = next(p for p in SocketsProbe.paths if p.name == "fentry")
    for kprobes, asked, mode in ((True, False, sockets.SPLICE_BY_KPROBES), (True, True, sockets.SPLICE_BY_KPROBES),
                                 (False, False, sockets.SPLICE_UNCOUNTED), (False, True, sockets.SPLICE_BY_SYSCALLS)):
        probe = SocketsProbe(Kernel(LINUX_6_6, kprobes=kprobes), ProcessTable(), splice_tracepoints=asked)
        assert probe.splice_reads == mode
        assert probe.caveat(tp_btf) == (sockets.SPLICE_UNCOUNTED_WHY if mode == sockets.SPLICE_UNCOUNTED else "")
        assert probe.caveat(fentry) == ""  # its fexit programs count splices
        extra = [a for a in probe.attachments(tp_btf) if a not in tp_btf.attachments]
        assert [kind for kind, _, _ in extra] == {
            sockets.SPLICE_BY_KPROBES: ["kprobe_link", "kretprobe_link"] * 2,
            sockets.SPLICE_BY_SYSCALLS: ["tracepoint"] * 2, sockets.SPLICE_UNCOUNTED: []}[mode]


def test_ubuntu_22_04_uses_fentry_then_kprobes():
    name, reasons = chosen(Kernel(LIFECYCLE, kprobes=True, fentry=True))
    assert name == "fentry"
    assert reasons == [f"{path}: no tracepoint sock_send_length, sock_recv_length" for path in ("tp_btf", "raw_tracepoint")]
    assert chosen(Kernel(LIFECYCLE, kprobes=True, fentry=False))[0] == "kprobe"


def test_before_linux_5_10_the_sockets_probe_has_no_ebpf_path():
    """The agent forgets a socket freed without a tracepoint by running a program itself
    (BPF_PROG_TEST_RUN of a raw tracepoint program, Linux >= 5.10): Ubuntu 20.04's 5.8 kernel has
    fentry and kprobes, and the sockets probe falls back to sock_diag there, saying why."""
    kernel = Kernel(LIFECYCLE, kprobes=True, fentry=True)
    kernel.__dict__["kernel_release"] = "5.8.0-63-generic"
    name, reasons = chosen(kernel)
    assert name is None
    assert reasons[2:] == [f"{path}: the agent cannot run BPF programs itself (BPF_PROG_TEST_RUN, Linux >= 5.10)"
                           for path in ("fentry", "kprobe")]


def test_no_path_says_why_for_each():
    name, reasons = chosen(Kernel(LIFECYCLE))
    assert name is None
    assert [r.split(":")[0] for r in reasons] == ["tp_btf", "raw_tracepoint", "fentry", "kprobe"]
    assert "CONFIG_KPROBES" in reasons[3]


def test_doctor_reports_this_machine_as_platform_md_says():
    out = subprocess.run([sys.executable, "-m", "drums", "doctor"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stderr == ""
    lines = out.stdout.splitlines()
    line = {l.split()[1]: l for l in lines if l[:3] in ("ok ", "NO ")}
    # The development machines (Debian 12, kernel 6.18): kprobes NOT available, fentry refused with EPERM, tracepoints work.
    assert line["kprobes"].startswith("NO ") and "CONFIG_KPROBES" in line["kprobes"]
    assert line["fentry"].startswith("NO ") and "refused" in line["fentry"]
    assert line["tp_btf"].startswith("ok ")
    assert line["tracepoints"].startswith("ok ")
    assert line["BTF"].startswith("ok ")
    for probe, path in (("sockets", "tp_btf"), ("sched", "tp_btf"), ("tcp", "raw_tracepoint")):
        assert any(l.strip().startswith(f"probe {probe}") and f"will use {path} " in l for l in lines)


def test_doctor_as_an_ordinary_user_tells_no_permission_from_not_mounted():
    """tracefs is mounted here, and closed to other users (mode 700): not "not mounted"."""
    out = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                          sys.executable, "-m", "drums", "doctor"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    at = next(i for i, l in enumerate(lines) if l.split()[1:2] == ["tracefs"])
    assert lines[at:at + 2] == ["NO  tracefs      /sys/kernel/tracing is mounted but not readable as uid 65534",
                                "    fix: run the agent (and this doctor) as root"]
    assert any(l.startswith("ok  bpffs") for l in lines)


def test_bpf_atomics_are_told_by_the_kernel_release():
    def kernel(release):
        k = Features()
        k.__dict__["kernel_release"] = release
        return k.bpf_atomics
    assert [kernel(r) for r in ("6.18.44-fc-v669", "5.12.0", "5.11.22-generic", "4.19.0-27-amd64", "odd")] == [
        True, True, False, False, False]


def test_before_linux_5_15_the_rtps_probe_traces_each_calls_entry_too():
    from drums.probes.rtps import RtpsProbe
    calls = {f"sys_{side}_{call}" for side in ("enter", "exit") for call in ("sendto", "sendmsg", "recvfrom", "recvmsg")}
    new, old = Kernel(calls), Kernel(calls)
    new.__dict__["task_pt_regs"], old.__dict__["task_pt_regs"] = True, False
    path, reasons = choose_path(RtpsProbe.paths, new)
    assert (path.defines, reasons) == ((), [])
    assert {fn for _, _, fn in path.attachments} == {f"on_{c}" for c in ("sendto", "sendmsg", "recvfrom", "recvmsg")}
    path, reasons = choose_path(RtpsProbe.paths, old)
    assert path.defines == (("SYSCALL_ENTRIES", 1),) and len(path.attachments) == 8
    assert reasons == ["tracepoint: no bpf_task_pt_regs to read a call's arguments at its exit (Linux >= 5.15)"]


def test_on_preempt_rt_the_sockets_probe_takes_kprobes_before_trampolines():
    rt = Kernel(LIFECYCLE, kprobes=True, fentry=True)
    rt.__dict__["preempt_rt"] = True
    name, reasons = chosen(rt)
    assert name == "kprobe" and reasons[2].startswith("fentry: PREEMPT_RT: a preempted trampoline"), reasons
    rt.__dict__["kprobes"] = False  # trampolines, if they are all there is
    assert chosen(rt)[0] == "fentry"
