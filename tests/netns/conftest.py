"""The real-mesh tier's tests live here and beside the features they test (marked `netns`): the
skip where namespaces cannot be made, the machine-wide lock and the check that a test leaves no
namespace behind are tests/conftest.py's, so they hold for every marked test wherever it is."""
