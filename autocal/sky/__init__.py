"""Sky models and antenna beams: what the antenna looks at and how it sees it."""
