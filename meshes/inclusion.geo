// A stiff circular inclusion in a softer square plate (2D, two materials).
// Bottom clamped, top loaded; outline and inclusion interface matched.
// Parameters: h (element size), r (inclusion radius).
DefineConstant[ h = 0.5, r = 2.0 ];
SetFactory("OpenCASCADE");
Rectangle(1) = {-5, -5, 0, 10, 10};
Disk(2) = {0, 0.5, 0, r, r};
BooleanFragments{ Surface{1}; Delete; }{ Surface{2}; Delete; }
// After fragmenting: the disk keeps tag 2, the plate with a hole becomes tag 3 (or 1).
eps = 1e-6;
plate() = Surface In BoundingBox{-5 - eps, -5 - eps, -eps, 5 + eps, 5 + eps, eps};
plate() -= {2};
bottom() = Curve In BoundingBox{-5 - eps, -5 - eps, -eps, 5 + eps, -5 + eps, eps};
top() = Curve In BoundingBox{-5 - eps, 5 - eps, -eps, 5 + eps, 5 + eps, eps};
left() = Curve In BoundingBox{-5 - eps, -5 - eps, -eps, -5 + eps, 5 + eps, eps};
right() = Curve In BoundingBox{5 - eps, -5 - eps, -eps, 5 + eps, 5 + eps, eps};
ring() = Boundary{ Surface{2}; };
Physical Surface("matrix") = {plate()};
Physical Surface("inclusion") = {2};
Physical Curve("bottom") = {bottom()};
Physical Curve("top") = {top()};
Physical Curve("outline") = {bottom(), right(), top(), left()};
Physical Curve("interface") = {ring()};
MeshSize{ PointsOf{ Surface{2}; } } = h / 2;
// Quadratic (curved) elements: every P2 node of the interface lies on the true circle,
// so all nodes can be compared with a target drawn on it (a straight-sided mesh's edge
// midpoints would sit on chords, up to their sag inside it).
Mesh.ElementOrder = 2;
