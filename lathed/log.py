"""structlog, configured once: JSON lines for journald, readable on a terminal.

The standard-library loggers of pymodbus, python-can and asyncua go through the same
renderer, so every line of the daemon has one format.
"""
from __future__ import annotations

import logging
import sys

import structlog


def setup(level: str = "info", json_lines: bool | None = None) -> None:
    if json_lines is None:
        json_lines = not sys.stderr.isatty()
    renderer = structlog.processors.JSONRenderer() if json_lines else structlog.dev.ConsoleRenderer(colors=False)
    shared = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    structlog.configure(
        processors=[*shared, structlog.stdlib.ProcessorFormatter.wrap_for_formatter],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=True,
    )
    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=[*shared, structlog.stdlib.add_logger_name],
        processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta,
                    structlog.processors.format_exc_info, renderer],
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(formatter)
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    # the libraries are chatty at debug; their warnings and errors matter
    for noisy in ("pymodbus", "can", "asyncua"):
        logging.getLogger(noisy).setLevel(max(logging.WARNING, root.level))
    # an OPC UA client's refused session or lost link is one line of the driver's (opcua_cnc):
    # the library's own account of it (the fault, the channel it could not close) is the same
    logging.getLogger("asyncua.client").setLevel(max(logging.ERROR, root.level))
