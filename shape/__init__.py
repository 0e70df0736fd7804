"""The shape analysis (``phantom.shape``): the paper's 3D VAE of prostate shapes, the average, the clusters and
the latent distance.

Modules: :mod:`~phantom.shape.dataset` (the pelvic MRI dataset's layout, folders of masks or meshes, the shape
grids), :mod:`~phantom.shape.synthetic` (a synthetic population in that layout), :mod:`~phantom.shape.voxels`
(resampling, voxelising, marching cubes), :mod:`~phantom.shape.vae` (the network), :mod:`~phantom.shape.training`
(training and the run folder), :mod:`~phantom.shape.analysis` (encode, decode, average, clusters),
:mod:`~phantom.shape.compare` (ICP, closest-point and latent distances), :mod:`~phantom.shape.figures` (heatmaps)
and :mod:`~phantom.shape.report`. It imports the model (for the phantom's body and surface geometry) and nothing
of scan, host or hil; JAX, nibabel and scikit-image come with the ``[shape]`` extra. See shape/README.md.
"""
