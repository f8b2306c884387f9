"""Files in and out: readers of users' surfaces and landmarks, writers of results, result folders written safely."""
