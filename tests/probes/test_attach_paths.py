"""The sockets probe's kprobe path cannot attach on this kernel (no CONFIG_KPROBES), but its
programs can still be compiled and put through the kernel's verifier, which is what this checks.
The fentry path cannot even load here (the kernel refuses BPF trampolines): it is untested."""
import os

from drums.kernel.loader import BPF_DIR
from drums.probes.bpf import ATTACH_DEFINES
from drums.probes.sockets import SocketsProbe


def test_kprobe_path_compiles_and_passes_the_verifier(features, proctable):
    os.environ["BCC_KERNEL_SOURCE"] = features.kernel_headers
    from bcc import BPF

    probe = SocketsProbe(features, proctable)
    (path,) = [p for p in probe.paths if p.name == "kprobe"]
    defines = dict(probe.offsets(features.btf), DRUMS_ATTACH=ATTACH_DEFINES["kprobe"])
    b = BPF(src_file=os.path.join(BPF_DIR, probe.source).encode(),
            cflags=[f"-D{k}={v}" for k, v in defines.items()] + [f"-I{BPF_DIR}"])
    try:
        functions = [fn for kind, _, fn in path.attachments if kind in ("kprobe", "kretprobe")]
        assert len(functions) == 7
        for fn in functions:
            assert b.load_func(fn.encode(), BPF.KPROBE).fd >= 0, fn
    finally:
        b.cleanup()
