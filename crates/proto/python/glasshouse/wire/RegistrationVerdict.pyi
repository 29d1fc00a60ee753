from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from typing import cast

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class RegistrationVerdict(object):
  Skipped = cast(int, ...)
  Applied = cast(int, ...)
  KeptAsSent = cast(int, ...)
  Rejected = cast(int, ...)

