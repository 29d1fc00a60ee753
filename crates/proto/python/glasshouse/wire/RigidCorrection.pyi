from __future__ import annotations

import flatbuffers
import numpy as np

import typing
from glasshouse.wire.Vec3d import Vec3d

uoffset: typing.TypeAlias = flatbuffers.number_types.UOffsetTFlags.py_type

class RigidCorrection(object):
  @classmethod
  def SizeOf(cls) -> int: ...

  def Init(self, buf: bytes, pos: int) -> None: ...
  def TranslationM(self, obj: Vec3d) -> Vec3d: ...
  def RotationVectorRad(self, obj: Vec3d) -> Vec3d: ...

def CreateRigidCorrection(builder: flatbuffers.Builder, translationM_x: float, translationM_y: float, translationM_z: float, rotationVectorRad_x: float, rotationVectorRad_y: float, rotationVectorRad_z: float) -> uoffset: ...

