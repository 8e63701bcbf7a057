"""Poses of overlapping thin parts in a bin (paper 001): instances from masks or depth steps
(`instances`), a pose per instance (`pose`), duplicates merged, pick order and the poses file
(`picking`)."""
