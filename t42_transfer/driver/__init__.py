"""What every hand driver shares, simulated or real: the commands it accepts and the steps it applies."""
