"""Independent oracles the tests check the model against: scikit-fem, FElupe and closed forms."""
