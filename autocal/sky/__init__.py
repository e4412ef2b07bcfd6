"""Sky models and antenna beams: what the antenna looks at and how it sees it.

:mod:`~autocal.sky.models` holds the sky models; the beams are
:mod:`~autocal.sky.beam_base` (the interface and conventions),
:mod:`~autocal.sky.analytic_beams`, :mod:`~autocal.sky.file_beams` and
:mod:`~autocal.sky.beam_names` (:func:`~autocal.sky.beam_names.get_beam`).
"""
