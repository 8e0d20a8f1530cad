"""Time meshes: the reference slab mesh and its boundary tags."""
from fem_dual.meshes.time_mesh import END, START, SlabMesh, slab_mesh

__all__ = ["START", "END", "SlabMesh", "slab_mesh"]
