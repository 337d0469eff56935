"""The SICK LMS 200 serial telegram protocol: bytes ↔ telegrams, no I/O.

* :mod:`~sensors.lms200.protocol.telegram` — constants, :class:`ProtocolError`, the checksum
  and framing;
* :mod:`~sensors.lms200.protocol.commands` — the ``cmd_*`` command builders and
  :class:`LmsConfig`;
* :mod:`~sensors.lms200.protocol.stream` — :class:`StreamParser` and the events it yields;
* :mod:`~sensors.lms200.protocol.scan` — measured values (``B0``): :class:`Scan`,
  :func:`decode_scan`, :func:`encode_scan`;
* :mod:`~sensors.lms200.protocol.plausibility` — :class:`ScanCheck`: checksum-valid scans that
  the configured sensor cannot send, rejected by reason;
* :mod:`~sensors.lms200.protocol.replies` — the other replies: :func:`decode_reply`, the
  ``encode_*_reply`` functions.

Import names from the module that defines them; this package re-exports nothing.
Reference: docs/lms200-protocol.md (sections cited as §n).
"""
