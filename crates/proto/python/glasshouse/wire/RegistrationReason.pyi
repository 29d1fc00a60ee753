from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from typing import cast

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class RegistrationReason(object):
  None_ = cast(int, ...)
  Disabled = cast(int, ...)
  MapTooSmall = cast(int, ...)
  TooFewPoints = cast(int, ...)
  NewGround = cast(int, ...)
  BelowResolution = cast(int, ...)
  ContradictsMap = cast(int, ...)
  TooFewInliers = cast(int, ...)
  LowInlierShare = cast(int, ...)
  RmsNotImproved = cast(int, ...)
  CorrectionTooLarge = cast(int, ...)
  NotConverged = cast(int, ...)
  Degenerate = cast(int, ...)

