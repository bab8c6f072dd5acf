"""From renders to bucket exposures to reads: the render plan, accumulation, the sensor stage, resources and tiles, the film store, the Dask cluster."""
