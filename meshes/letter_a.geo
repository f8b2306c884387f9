// Capital letter A with its triangular hole (the paper's 2D scene, Figs. 3-5).
// Units: cm. Feet clamped, top loaded, whole outline (hole included) matched.
// Parameter: h (element size), set from Python with gmsh.parser.setNumber.
DefineConstant[ h = 0.4 ];

// Outer contour, counter-clockwise from the left foot.
Point(1) = {0.0, 0.0, 0, h};   Point(2) = {1.6, 0.0, 0, h};
Point(3) = {2.32, 2.4, 0, h};  Point(4) = {5.68, 2.4, 0, h};
Point(5) = {6.4, 0.0, 0, h};   Point(6) = {8.0, 0.0, 0, h};
Point(7) = {5.0, 10.0, 0, h};  Point(8) = {3.0, 10.0, 0, h};
// Hole: between the inner leg edges, above the cross bar.
Point(9) = {2.68, 3.6, 0, h};  Point(10) = {5.32, 3.6, 0, h};  Point(11) = {4.0, 8.0, 0, h};

Line(1) = {1, 2};  Line(2) = {2, 3};  Line(3) = {3, 4};  Line(4) = {4, 5};
Line(5) = {5, 6};  Line(6) = {6, 7};  Line(7) = {7, 8};  Line(8) = {8, 1};
Line(9) = {9, 11}; Line(10) = {11, 10}; Line(11) = {10, 9};

Curve Loop(1) = {1, 2, 3, 4, 5, 6, 7, 8};
Curve Loop(2) = {9, 10, 11};
Plane Surface(1) = {1, 2};

Physical Surface("letter") = {1};
Physical Curve("feet") = {1, 5};
Physical Curve("top") = {7};
Physical Curve("outline") = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11};
