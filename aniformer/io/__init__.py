"""Reading and writing what users bring and take: meshes (`mesh`), glTF (`glb`, skinned: `rigged_glb`), BVH
(`bvh`), previews (`render`), the evaluation's tables and plot (`report`) and atomic files (`files`). The model
core never imports it."""
