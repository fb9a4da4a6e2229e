"""The method: the paper's discretisation and step (Taylor-Hood Navier-Stokes, membranes, the transfer between
mesh and membrane points, the FE-IB step, its time steps and health checks, the plain reference step)."""
