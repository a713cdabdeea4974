"""The session file format's name and version (docs/session.md), read by the writer, the reader
and the indexer alike."""

__all__ = ["FORMAT", "FORMAT_VERSION"]

FORMAT = "dmarionette-session"
FORMAT_VERSION = 2  # 2: wall-clock log times (log_time_origin_ns), Foxglove channels
