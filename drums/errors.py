"""The one error hierarchy of Drums: the CLI turns any DrumsError into one line and exit code 2."""


class DrumsError(Exception):
    """Base of every error Drums reports to a user."""


class UsageError(DrumsError):
    """A bad flag, config value, PID or port."""


class KernelError(DrumsError):
    """The kernel lacks something a probe needs (BTF, a tracepoint, privileges, bpffs)."""


class ProbeError(DrumsError):
    """A probe failed to load, attach or read its maps."""


class GraphError(DrumsError):
    """A middleware or graph description could not be read: garbage, no answer, a bad file."""
