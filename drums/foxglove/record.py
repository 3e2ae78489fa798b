"""`drums record --output FILE.mcap`: the channels of one or more agents (drums.foxglove.channels)
written to an MCAP file as they come, until SIGINT or SIGTERM, which close it with its summary and
index. Chunks are kept small and written whole, so that a recorder killed outright leaves a file
whose every chunk but the last is read back (by a reader that does not need the summary, as mcap's
NonSeekingReader in file order)."""
from __future__ import annotations

from drums.errors import DrumsError, UsageError
from drums.foxglove.channels import follow
from drums.top.collector import Collector

CHUNK = 16 * 1024  # bytes of messages a chunk holds: seconds of a robot's hundred channels


class RecordError(DrumsError):
    pass


def run(urls: list[str], token: str, interval: float, output: str, detector: str = "") -> int:
    import foxglove
    from foxglove.mcap import MCAPWriteOptions
    collector = Collector(urls, token, interval, detector)  # (which checks the URLs first)
    context = foxglove.Context()
    try:
        # Each chunk written whole once it is full (not begun in the file and its length written last):
        # a recorder killed outright leaves every chunk but the one it was filling.
        writer = foxglove.open_mcap(output, context=context,
                                    writer_options=MCAPWriteOptions(chunk_size=CHUNK, disable_seeking=True))
    except Exception as e:  # the SDK raises its own errors for a path it cannot create
        raise UsageError(f"--output {output}: {e}") from None
    try:
        follow(collector, context, interval)
    finally:
        try:
            writer.close()
        except Exception as e:  # a full disk: the chunks written stay readable
            raise RecordError(f"{output}: the recording could not be closed ({e}); what was written before is readable") from None
    return 0
