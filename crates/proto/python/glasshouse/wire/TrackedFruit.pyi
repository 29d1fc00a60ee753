from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from glasshouse.wire.Vec3 import Vec3

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class TrackedFruit(object):
  @classmethod
  def SizeOf(cls) -> int: ...

  def Init(self, buf: bytes, pos: int) -> None: ...
  def Id(self) -> int: ...
  def Centre(self, obj: Vec3) -> Vec3: ...

def CreateTrackedFruit(builder: flatbuffers.Builder, id: int, centre_x: float, centre_y: float, centre_z: float) -> uoffset: ...

