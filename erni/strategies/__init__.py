"""Deployment strategies as pure functions over numpy arrays (no blackboard, no clock, no I/O).

- `widep`: PoI coverage keeping RNG connectivity (paper 000, Algorithm 1).
- `potential`: potential-field self-deployment, equations (15) and (16) of paper 001.
- `relay`: relay positioning between a source and a destination (paper 000, 5.2).
- `patrol`: territory blocks, sweep paths, heartbeat silence and takeover (paper 002, II.C).
- `energy`: the robots' energy model (paper 000, 5.3).

MissionControl calls these on the robot; the simulator calls them for whole teams at once.
"""
