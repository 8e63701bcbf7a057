"""Poses of overlapping thin parts in a bin (paper 001): instances from masks or depth steps
(`instances`), the part's model from its mesh (`part_model`), each instance in its own plane
(`instance_plane`), a pose per instance (`pose`, tuned by `pose_settings`), duplicates merged,
pick order and the poses file (`picking`)."""
