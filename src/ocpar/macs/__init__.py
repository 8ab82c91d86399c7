"""Multi-objective optimal control with Multi Agent Collaborative Search (MACS)."""
