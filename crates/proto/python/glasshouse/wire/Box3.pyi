from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from glasshouse.wire.Vec3 import Vec3

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class Box3(object):
  @classmethod
  def SizeOf(cls) -> int: ...

  def Init(self, buf: bytes, pos: int) -> None: ...
  def Min(self, obj: Vec3) -> Vec3: ...
  def Max(self, obj: Vec3) -> Vec3: ...

def CreateBox3(builder: flatbuffers.Builder, min_x: float, min_y: float, min_z: float, max_x: float, max_y: float, max_z: float) -> uoffset: ...

