"""IMU preintegration between AoA epochs."""
