"""DICOM networking both ends of this project share: pynetdicom associations with its defects worked around.

* :mod:`dicomnet.scu`: the calling side (an SCU association whose reactor cannot steal a response).
  Used by the PACS export (:mod:`service.navigation.pacs.scu`), the mock O-arm's C-STORE push
  (:mod:`mocks.oarm.cstore`) and the test peers.
* :mod:`dicomnet.server`: the listening side (``poll`` instead of ``select``, a failed ``accept``
  reported).  Used by the service's Storage SCP (:mod:`service.intake.storage_scp`).

Why a package of its own: the mocks may import it (they may not import ``service``) without the
robot links of ``drivers/``, and both halves of the same workarounds sit together here, below every
package that uses them.  What a peer stores, refuses or exports stays with its user
(``service/intake``, ``service/navigation/pacs``, ``mocks/oarm``).

May import only the standard library and pynetdicom (design.md §2; tests/unit/test_import_layers.py).
"""
