"""Registry of scene representations F (``FieldConfig.encoding``); entries are ``Field`` classes taking
``(cfg: FieldConfig, bounds: np.ndarray (3,2))``. They register in ``inrslam.fields.models``, which the
package ``inrslam.fields`` imports, so importing this module through the package always sees all names."""

from __future__ import annotations

from inrslam.registry import Registry

ENCODINGS: Registry = Registry("encoding")
