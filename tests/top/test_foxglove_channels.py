"""The anomalies of a `drums detect` as Foxglove Log messages (drums.foxglove.channels): each once,
when it starts, stamped with its start, in the detector's words. (The rows' channels are read back
from real recordings and servers in tests/graph/test_record.py and test_foxglove.py.)"""
from drums.foxglove.channels import ANOMALIES, Channels, log_message
from drums.top.model import Frame


def anomaly(start: float, series: str) -> dict:
    return {"entity": {"kind": "edge", "name": "/image /camera -> /processor", "host": "arm"},
            "anomalies": [{"series": series, "start": start, "what": "received bytes", "change": "-82%",
                           "checks": ["a", "b", "c", "d"], "text": f"edge /image: received bytes -82% ({series})"}]}


def test_each_anomaly_is_one_warning_log_message_when_it_starts():
    channels = Channels()
    frame = Frame(at=1000.0, interval=1.0, agents=[], anomalies={"incidents": [{"entities": [anomaly(990.5, "rx")]}]})
    [m] = channels.messages(frame)
    assert (m.topic, m.at_ns, m.schema) == (ANOMALIES, 990_500_000_000, {})
    assert m.value == {"timestamp": 990.5, "level": "Warning", "message": "edge /image: received bytes -82% (rx)",
                       "name": "arm"}
    log_message(m.value).encode()  # a foxglove.Log the SDK takes
    later = Frame(at=1001.0, interval=1.0, agents=[],
                  anomalies={"incidents": [{"entities": [anomaly(990.5, "rx"), anomaly(1000.75, "tx")]}]})
    assert [m.value["message"] for m in channels.messages(later)] == ["edge /image: received bytes -82% (tx)"]
