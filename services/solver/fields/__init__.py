"""The neural fields (PyTorch). Their typed configuration is :mod:`schemas.solver`.

``encoding``    field components: multiresolution hash grid of position, spherical harmonics
``mlp``         the fully connected network
``field``       ``NeuralField``: encodings + MLP + output scale; ``L_phi`` has 3 outputs,
                ``dL_theta`` has one per (active scalar, RGB channel it can change) pair
"""
