"""Depth-uncertainty products of a trained run, for planners, viewers and mapping pipelines.

Layers (each module one job; heavy libraries are imported where they are used):

    depth_maps    K per-draw depths -> camera-z mean / std (epistemic, spread, total) / opacity /
                  quantile maps; writers for .npz, 16-bit PNG + JSON scale, float32 TIFF, colourised PNG
    free_space    P(depth > d) from the draws, per pixel and as a [T, H, W] volume
    pointcloud    back-projection (kornia), normals, per-point depth_std / depth_var / confidence /
                  opacity / covariance, filters, colours, Open3D clouds, binary PLY
    fusion        inverse-variance fusion of many views' clouds per voxel
    render_cloud  offscreen picture of a cloud coloured by uncertainty
    export        the ``stochastic-fields export`` driver (cameras, files, summary.json)
    cli           its command-line options

For robots (each read back in the tests with the consumer's own library):

    ros_depth      REP 118 depth images (float metres, uint16 millimetres) + std + CameraInfo
                   (integer pixel centres), metric scale handling, Open3D TSDF integration
    occupancy_map  P(voxel blocked) in closed form from the rectified normal; sparse npz + OctoMap .ot
    free_path      P(segment / path collision-free) from K density trajectories, with its MC error
    plan           risk-weighted voxel paths on an occupancy map
    rosbag         ROS 2 bag of an export (rosbags: Image, CameraInfo, PointCloud2, TF)
    rerun_log      rerun .rrd recording of an export
    planner_cli, free_path_cli   the ``occupancy`` and ``free-path`` commands

Conventions: every depth is camera-z depth in scene units (docs/definitions.md §1); cameras are OpenCV with
pixel centres at +0.5; see ``depth_maps.CONVENTIONS`` (also written into every file).
"""
