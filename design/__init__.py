"""A phantom from a patient's shape (the paper's design step): a gland's surface from an MRI label mask or a closed
mesh, three chambers placed in its anatomy, a tagged tetrahedral mesh and a scene the model accepts, and the
lost-wax cast (mould halves and wax cores) as printable STLs. ``phantom design`` runs it
(:func:`phantom.design.pipeline.design`)."""
