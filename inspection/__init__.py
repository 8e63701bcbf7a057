"""Inspection against CAD: a measured cloud registered to the part's STEP model (or a mesh),
segmented by CAD face, each face's form errors evaluated, and the result reported.

Modules (each one job):
    errors        InspectionError and its kinds (CadError, CloudError, UnitMismatch, RegistrationFailed, ...)
    surfaces      exact plane/cylinder/cone/sphere/torus/B-spline surfaces, vectorised evaluation and projection
    cad           STEP (OpenCASCADE) and mesh models: faces with STEP ids, types, parameters, trimming; units
    sampling      area-uniform labelled points on the exact faces
    measured_cloud measured clouds: sessions, PLY/PCD/XYZ, normals, the part isolated from its table, unit check
    features      FPFH (Open3D) and SHOT (vectorised) descriptors
    registration/ scan-to-model pose, one module per stage: settings, rigid, clouds, spheres (RSCS), target,
                  matching (Eq. 11), sac_ia, ndt, hypotheses, verification, point_to_plane (ICP),
                  gauss_newton, face_bias, fine; driver (`register`)
    segmentation  every point assigned to its CAD face (distance, normal, inside the face), signed deviations
    form          least-squares and minimum-zone flatness/cylindricity, Gaussian regression filter, Sq, noise floors,
                  deviations and profile zone of the form surface
    tolerances    per-face limits and ISO 14253-1 verdicts
    report        the per-face table as JSON, CSV, text and HTML with the deviation map
    inspection_recording  the result in the session's Rerun recording
    inspect_scan  scan + model -> report
    downsample    voxel averaging and paper 001's density-centre selection (shared with bins/ and regions/)

Two more products stand on the same base: `bins/` (poses of overlapping thin parts in a bin,
paper 001: instances, part_model, instance_plane, pose_settings, pose, picking) and `regions/`
(context-free region growing, paper 002: region_growing, local_features, segmetrics).
"""
