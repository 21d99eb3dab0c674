"""Monte Carlo sampling on Mitsuba/Dr.Jit (the only package besides ``scene`` and ``estimators``
that touches Dr.Jit types).

``surface``    residual points ``(x, ω_o)`` uniform by area over the residual domain (Eq. 8)
``delta``      rays followed through ideal-specular surfaces to the first non-delta hit
``incident``   the one-bounce MIS estimate of the incident integrals of Eq. 5 and Eq. 6 (Eq. 9)
``camera``     primary rays of a sensor and splatting of per-ray values into its film
``tensors``    conversion of Dr.Jit lanes into torch tensors (field queries)
``passes``     splitting a sample count into passes of bounded width
"""
