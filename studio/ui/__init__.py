"""The viser browser app: panels, scene mirroring, teleop, imitation and the rollout inspector."""
