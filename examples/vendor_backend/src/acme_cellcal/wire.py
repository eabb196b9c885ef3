"""The ACME Z1's wire protocol over TCP (what a vendor SDK would otherwise hide).

All integers little-endian. The client sends 8-byte requests ``<4sI``: a command and
one argument. The device answers each request with a 12-byte header ``<4sII`` — a
reply kind, a number, the body length in bytes — and the body:

==========  ===============  ==========================================================
request     reply kind       body
==========  ===============  ==========================================================
``INFO 0``  ``Z1IN 0``       UTF-8 JSON: serial, firmware, width, height, fx, fy, cx, cy
``GRAB t``  ``Z1FR <id>``    ``<HHQ`` width, height, timestamp (µs since the Unix epoch),
                             then ``width * height`` uint16 Z-depths in millimetres
                             (0 = no return), row-major; waits at most ``t`` ms
any         ``Z1ER <code>``  UTF-8 text; code 408 = no frame within ``t`` ms
==========  ===============  ==========================================================
"""

from __future__ import annotations

import struct

REQUEST = struct.Struct("<4sI")
HEADER = struct.Struct("<4sII")
FRAME_HEAD = struct.Struct("<HHQ")

CMD_INFO = b"INFO"
CMD_GRAB = b"GRAB"
REPLY_INFO = b"Z1IN"
REPLY_FRAME = b"Z1FR"
REPLY_ERROR = b"Z1ER"

#: Error code of a GRAB that found no frame within its wait.
CODE_NO_FRAME = 408
#: Largest image the Z1 sends, pixels.
MAX_WIDTH, MAX_HEIGHT = 640, 480
#: Largest reply body the client accepts, bytes (a full-size frame).
MAX_BODY = FRAME_HEAD.size + 2 * MAX_WIDTH * MAX_HEIGHT
