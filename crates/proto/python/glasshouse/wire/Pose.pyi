from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from glasshouse.wire.Quat import Quat
from glasshouse.wire.Vec3d import Vec3d

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class Pose(object):
  @classmethod
  def SizeOf(cls) -> int: ...

  def Init(self, buf: bytes, pos: int) -> None: ...
  def Translation(self, obj: Vec3d) -> Vec3d: ...
  def Rotation(self, obj: Quat) -> Quat: ...

def CreatePose(builder: flatbuffers.Builder, translation_x: float, translation_y: float, translation_z: float, rotation_x: float, rotation_y: float, rotation_z: float, rotation_w: float) -> uoffset: ...

