"""Reading and writing what users bring and take: meshes (`mesh`), glTF (`glb`), BVH (`bvh`), previews
(`render`) and atomic files (`files`). The model core never imports it."""
