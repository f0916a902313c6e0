"""Register-level models of the GY-86's chips: MPU6050, HMC5883L, MS5611."""
