"""`drivesim synth`: a procedural road world with ground truth, and a drive through it as a ROS2 MCAP recording.

Public API:
    SynthConfig                              (config.py) the stage config; preset configs/synth.yaml
    SynthWorld.from_seed(seed, cfg)          (world.py) the world; .render(T_world_camera, K, w, h) -> (rgb, depth_m),
                                             .render_full(...) adds semantic ids; .path / .road (RoadPath); .camera
    SynthWorld.from_sidecar(path)            rebuild the world of a recording from <recording>.world.json
    Trajectory(world.path, cfg.drive)        (drive.py) the ego motion: .state(t_s), .vehicle_pose(t_s)
    synthesize(cfg, output, preview)         (synthesize.py) the whole stage: world, sensors, render, MCAP, previews
Topics of the recording: recording.py.
"""
