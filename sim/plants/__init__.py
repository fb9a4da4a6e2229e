"""The plants of the closed loop: their contract (``contract``: what the controller may import), their registry
(``registry``) and one module per plant model."""
