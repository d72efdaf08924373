"""Layer 2, operations: pure per-element kernels on gathered stencils (no modules, no validation).

``hinge`` (bend angle, its gradient, HVP and 12x12 blocks), ``psi`` (the bending models and the
per-hinge scalar energy with its derivatives), ``triangle`` (the per-triangle Hessian, paper eq. 7),
``membrane`` (deformation gradients, densities and closed-form eigensystems), ``projection`` (PSD
projections of blocks), ``stencil`` (gather/scatter, chunking, the degenerate-triangle test).
"""
