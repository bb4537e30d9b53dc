"""Agents: history encoders, replay buffers and learners (SAC, PPO) in PyTorch."""
