"""What every worker process of the station is: how it allocates memory, and that it ends
with the station (job workers and the live workers alike)."""
