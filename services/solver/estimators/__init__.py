"""Estimators: the residuals that train the fields (Eq. 5, 6, 8, 9) and the five gradient
methods that turn fields and rays into gradient images ``dI/dp`` (Eq. 3, 10, 11)."""
