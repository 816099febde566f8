"""Errors and warnings of the calibration pipeline.

Every user-input problem raises a subclass of :class:`CalibrationInputError` (a ValueError,
so ``deltatwin`` prints it as one line and exits 2).  Conditions that do not stop the fit
but change what it sees (rows dropped, metadata missing) issue a named warning.
"""
from __future__ import annotations


class CalibrationInputError(ValueError):
    """Input data or arguments that the calibration cannot use as given."""


class MissingColumnsError(CalibrationInputError):
    """A column needed by the requested features is not in the table."""


class TooFewPointsError(CalibrationInputError):
    """Fewer calibration rows than the candidate terms need."""


class ValidationOverlapError(CalibrationInputError):
    """Validation positions also appear in the calibration set."""


class ModelMismatchError(CalibrationInputError):
    """A model file that does not match the requested features, kind or data."""


class ModelFileError(CalibrationInputError):
    """A model file that cannot be read or does not follow the model format."""


class CalibrationWarning(UserWarning):
    """Base of the calibration pipeline's warnings."""


class DroppedRowsWarning(CalibrationWarning):
    """Rows were left out of a fit or a prediction (NaN inputs or outputs)."""


class MissingMetadataWarning(CalibrationWarning):
    """Metadata was missing and a documented default was used instead."""


class NoValidationWarning(CalibrationWarning):
    """The data has no validation rows: validation figures are not available."""


class DegenerateColumnWarning(CalibrationWarning):
    """Candidate columns that are constant (fitted exactly by the intercept) or exact
    duplicates of an earlier column: never eligible to enter."""


class FitError(CalibrationInputError):
    """A physics fit that cannot be done as asked (effects, data) or did not converge."""


# ---------------------------------------------------------------------------------------------
# the data as a model sees it
