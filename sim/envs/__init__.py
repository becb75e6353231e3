"""The driving tasks as gymnasium environments: drivesim/Lane-v0, drivesim/Follow-v0, drivesim/Overtake-v0."""

from gymnasium.envs.registration import register, registry

ENV_IDS = {
    "lane": ("drivesim/Lane-v0", "drivesim.sim.envs.lane:LaneEnv"),
    "follow": ("drivesim/Follow-v0", "drivesim.sim.envs.follow:FollowEnv"),
    "overtake": ("drivesim/Overtake-v0", "drivesim.sim.envs.overtake:OvertakeEnv"),
}

for _env_id, _entry in ENV_IDS.values():
    if _env_id not in registry:
        # The episode length is the env's own (config.episode_steps, reported as truncation): no TimeLimit wrapper.
        register(id=_env_id, entry_point=_entry, disable_env_checker=True, order_enforce=False)
