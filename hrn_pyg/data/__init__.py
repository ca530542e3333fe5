"""Ground truth and its graphs: pybullet scenes, voxelised meshes, the particle -> cluster -> object
hierarchy as PyG ``HeteroData``, collision edges, episode files and training windows."""
