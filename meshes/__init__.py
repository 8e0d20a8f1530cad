"""Time meshes: the reference slab mesh, its boundary tags, and the partition of [0, T] into slabs."""
from fem_dual.meshes.time_mesh import END, START, SlabMesh, SlabSchedule, slab_mesh

__all__ = ["START", "END", "SlabMesh", "SlabSchedule", "slab_mesh"]
