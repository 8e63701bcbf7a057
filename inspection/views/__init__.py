"""The whole part from several views on a stage (issue 13).

    views (clouds of a multi-view session, each in its rig world frame)
      --prior: the stage pose of each view (calibrated axis)--> views in the part frame   align.py
      --refined pairwise (partial overlap, point-to-plane ICP)--> edges                  pairwise.py
      --global pose-graph optimisation over all views (Open3D)--> each view's pose        align.py
      --fused, each point weighted by its expected precision--> one merged cloud          merge.py
      --Poisson surface, trimmed to what the views saw--> mesh (PLY, STL)                 mesh.py

`view_clouds.py` reads the views and each point's expected precision (`precision.py`);
`recording.py` logs the merged cloud, the mesh and each view's pose to Rerun. The part frame
is the stage frame (the rig's world frame with the stage at 0: `scanner.multiview`).
"""
