"""The trace artifact (`<workspace>/trace/`): what `drivesim ingest` writes and every later stage reads.

Frames: camera optical (x right, y down, z forward); vehicle: x forward, y left, z up (REP-103), origin on the
ground below the rear axle where known (else below the IMU/GPS unit); times are int64 nanoseconds since the Unix
epoch (or since the recording's start when the source has no absolute time, see `calibration.json:time_base`).

Files (all arrays are .npy; N = frame count):
    frames.npy              uint8   (N, H, W, 3)  RGB, undistorted, at the working resolution; open with mmap_mode="r"
    frame_times_ns.npy      int64   (N,)          camera stamp of each frame, strictly increasing
    calibration.json        {
        "width_px": W, "height_px": H,            working resolution of frames.npy
        "K": [[fx,0,cx],[0,fy,cy],[0,0,1]],       pinhole intrinsics at the working resolution (pixels)
        "source_width_px", "source_height_px",    resolution of the recorded images
        "distortion_model": "plumb_bob" | "equidistant" | "none",  what was removed
        "T_vehicle_camera": 4x4,                  camera optical frame -> vehicle frame (metres)
        "camera_height_m": float | null,          camera optical centre above the ground
        "extrinsics_source": "tf_static" | "kitti_calib" | "config" | "default",
        "time_base": "unix" | "relative"
    }
    sources.json            {"recording": str, "format": "ros1" | "rosbag2" | "mcap" | "kitti_raw" | "kitti_odometry",
                             "camera_topic": str, "sensors": {name: {"topic", "type", "message_count"}}}
  Optional series (present when the recording has them; each an .npz of equal-length arrays):
    gps.npz       t_ns int64 (M,); lat_deg, lon_deg, alt_m float64 (M,); status int8 (M,) (NavSatStatus:
                  -1 no fix, 0 fix, 1 SBAS, 2 GBAS); covariance_m2 float64 (M,3,3) ENU position covariance;
                  covariance_type uint8 (M,)
    imu.npz       t_ns (M,); angular_velocity_radps float64 (M,3) and linear_acceleration_mps2 (M,3) in the vehicle
                  frame; orientation_xyzw float64 (M,4) (NaN when the source has none)
    speed.npz     t_ns (M,); speed_mps float64 (M,) forward speed (wheel odometry / TwistStamped / OXTS vf)
    odometry.npz  t_ns (M,); position_m float64 (M,3); orientation_xyzw (M,4); linear_velocity_mps (M,3) and
                  angular_velocity_radps (M,3) in the child (vehicle) frame
    poses.npz     t_ns (M,); T_world_camera float64 (M,4,4): given camera poses (KITTI odometry ground truth)
    ground_truth.npz  (synthetic recordings only) t_ns (M,); T_world_vehicle float64 (M,4,4) in the synth world's
                  ENU frame; depth at the frame times is in gt_depth.npy float32 (N,H,W) metres (inf = sky)
"""
