from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from typing import cast

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class Payload(object):
  NONE = cast(int, ...)
  RgbdFrame = cast(int, ...)
  ArmState = cast(int, ...)
  TrolleyInfo = cast(int, ...)
  RoiCloud = cast(int, ...)
  RankedViews = cast(int, ...)
  FruitEstimates = cast(int, ...)
  MapUpdate = cast(int, ...)
  PlannerStatus = cast(int, ...)
  TrolleyStatus = cast(int, ...)
  DetectorStatus = cast(int, ...)
  MapSnapshot = cast(int, ...)
  FleetFruits = cast(int, ...)

