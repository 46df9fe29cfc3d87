"""The field method (Wang et al. 2018, Optics and Precision Engineering 26(2)).

Initial values (:mod:`.dlt`, :mod:`.resection`, :mod:`.distortion_init`), the bundle
model (:mod:`.bundle`), identification of measured targets (:mod:`.identify`,
:mod:`.eccentricity`), the self-calibrating adjustment with blunder rejection and
parameter selection (:mod:`.adjustment`) and the whole chain from images
(:mod:`.from_images`). The field's data structures
are the session's (:mod:`fieldcal.session.data`).
"""
